"""Stage I, composed once: the frames, masks and vote of one scene, each a cached stage.

`compose_stage_one` is the one composition every command runs: an evaluation (`run_scene`),
`sagonline segment` (`segment_scene`), `sagonline export` and the diagnosis's counterfactual
vote. It returns the stages' outputs with their keys and what each stage did.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from sagonline.pipeline.graph import Output, StageCache, StageRun, run_stage
from sagonline.pipeline.stages import (
    FRAMES,
    MASKS,
    VOTE,
    FeedbackInputs,
    Frames,
    FramesInputs,
    MasksInputs,
    SegmenterRun,
    VoteInputs,
    label_count,
)
from sagonline.render.backends import BackendPlan, plan_backends
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import SegmentationResult
from sagonline.segment.prompts import Prompt
from sagonline.vote.consensus import VoteConfig, VoteResult
from sagonline.vote.feedback import FeedbackConfig


@dataclass
class PipelineSettings:
    """How a scene is run: the image renderer and the vote's implementation, each resolved on
    its own for the device (`render.backends.plan_backends`), the label render's threshold, the
    metrics' resize rule, progress bars, the render background, consensus feedback."""

    backend: str = "auto"
    vote_backend: str = "auto"
    device: str = "cpu"
    label_min_weight: float = 0.2
    resize: str = "pred_to_gt"
    progress: bool = True
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    diagnose: bool = True


@dataclass
class StageOneOutput:
    """What Stage I hands on (to scoring, Stage II, `segment` and `export`): the stages'
    outputs (with their keys), what each stage did (`computed` or `cached`, and seconds), the
    label count and the names of the views whose masks voted."""

    frames: Output[Frames]
    masks: Output[SegmentationResult]
    vote: Output[VoteResult]
    num_labels: int
    voted: set[str]
    runs: dict[str, StageRun] = field(default_factory=dict)
    backends: BackendPlan | None = None

    @property
    def labels(self) -> np.ndarray:
        """(N,) int64 labels per Gaussian: -1 unlabelled, 0 background, 1.. the objects."""
        return self.vote.value.assigned.cpu().numpy()

    @property
    def keys(self) -> dict[str, str]:
        return {"frames": self.frames.key, "masks": self.masks.key, "vote": self.vote.key}


def compose_stage_one(
    gaussians: Gaussians,
    trajectory: list[Camera],
    prompt: Prompt,
    segmenter: SegmenterRun,
    vote_cfg: VoteConfig,
    settings: PipelineSettings,
    *,
    num_labels: int,
    trajectory_gt: list[np.ndarray] | None = None,
    cache: StageCache | None = None,
    on_masks=None,
) -> StageOneOutput:
    """Stage I, the one composition every command runs (eval, `segment`, `export`): render the
    trajectory, segment it, vote the masks; each stage cached under the key of its inputs.

    gaussians: the scene on `settings.device`; trajectory: T cameras in video order; prompt:
    on one of its frames; num_labels: the labels the caller knows of (the masks may add more);
    trajectory_gt: T (H, W) label maps (read by the oracle only); on_masks(frames, masks,
    num_labels): called between the masks and the vote (a recorder keeps them even if the
    vote is interrupted)."""
    cache = cache or StageCache(None)
    progress = settings.progress
    plan = plan_backends(settings.backend, settings.vote_backend, settings.device)
    device = torch.device(plan.device).type
    runs: dict[str, StageRun] = {}
    frames_in = FramesInputs(
        gaussians, list(trajectory), plan.images, tuple(settings.background), device
    )
    frames, runs["frames"] = run_stage(FRAMES, frames_in, cache, progress)
    feedback = None  # with consensus feedback on, the masks also depend on what it votes with
    if settings.feedback.enabled:
        feedback = FeedbackInputs(
            settings.feedback, vote_cfg, gaussians, list(trajectory), num_labels,
            settings.label_min_weight, plan.vote,
        )  # fmt: skip
    masks_in = MasksInputs(frames, prompt, trajectory_gt, segmenter, feedback)
    masks, runs["masks"] = run_stage(MASKS, masks_in, cache, progress)
    labels = label_count(num_labels, masks.value.masks)
    if on_masks is not None:
        on_masks(frames.value.images, masks.value.masks, labels)
    vote_in = VoteInputs(
        masks, gaussians, list(trajectory), num_labels, vote_cfg, plan.vote, device
    )
    vote, runs["vote"] = run_stage(VOTE, vote_in, cache, progress)
    voted = {trajectory[i].name for i in vote.value.frames}
    return StageOneOutput(frames, masks, vote, labels, voted, runs, plan)
