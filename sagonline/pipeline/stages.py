"""The cached stages of one scene: frames -> masks -> vote, and the student's checkpoint.

Each stage's key digests every field of one inputs dataclass (`graph.Stage`), so what a stage
depends on is exactly what its inputs dataclass holds; Stage I's engine
(`stage_one.StageOne`) computes the first three, `stage_two` the student:
- frames: the scene, the trajectory cameras, the image renderer that ran and a digest of its
  sources, the background, the device;
- masks: the frames (by their key), the prompt, the trajectory's ground truth (the oracle
  reads it), the segmenter (settings, weight digests, its plug-in's version) and, with
  consensus feedback on, what the feedback votes and renders with;
- vote: the masks (by their key), the scene, the cameras, the label count, the vote settings
  and its rule's plug-in version, the vote backend that ran and a digest of its kernel, the
  device;
- refine: the frames, masks and vote (by their keys) and the student's settings: the key
  names the student's checkpoint (`stage_two`), which trains in the background.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sagonline.core.plugins import VOTE_RULES
from sagonline.core.provenance import digest_json
from sagonline.core.store import stored
from sagonline.pipeline.graph import Output, Stage
from sagonline.refine import RefineConfig
from sagonline.render.backends import implementation_digest
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import SegmentationResult, VideoSegmenter
from sagonline.segment.prompts import Prompt
from sagonline.vote.consensus import VoteConfig, VoteResult
from sagonline.vote.feedback import FeedbackInputs, advice_inputs


@stored
@dataclass
class Frames:
    """The rendered trajectory: T RGB uint8 (H, W, 3) images, and seconds per frame."""

    images: list[np.ndarray]
    seconds_per_frame: float


@dataclass(frozen=True)
class FramesInputs:
    gaussians: Gaussians  # on `device`
    cameras: list[Camera]  # the trajectory, in video order
    backend: str  # the image renderer that runs: native | torch | gsplat
    kernel: str  # render.backends.implementation_digest(backend)
    background: tuple[float, float, float]
    device: str  # cpu | cuda


@dataclass(frozen=True)
class SegmenterRun:
    """A segmenter with the settings it was built from and the digests of its weight files:
    what its masks depend on (the instance itself is not digested)."""

    segmenter: VideoSegmenter
    settings: dict = field(default_factory=dict)
    weights: dict[str, str] = field(default_factory=dict)  # path -> file digest

    def digest(self) -> str:
        return digest_json(
            self.segmenter.name,
            self.settings,
            sorted(self.weights.values()),
            self.segmenter.version,
        )


def segmenter_run(
    node: dict, corrupt=None, *, check: bool = True, untrusted: bool = False
) -> SegmenterRun:
    """The segmenter a config node names ({kind, name, its settings}), built from the registry
    (never from a class name in the node), its answers corrupted where `corrupt` (a
    MaskCorruption) is active, its weight files digested, and with `check` its weights opened
    now. `untrusted`: the node was read from a file someone else may have written (a run
    folder): `trust_checkpoint` is turned off whatever it says. The masks' key holds the node's
    settings as given, so every command that rebuilds a run's segmenter finds its masks."""
    from sagonline.core.plugins import NODE_KEYS, SEGMENTERS
    from sagonline.core.provenance import digest_file
    from sagonline.segment.corruption import CorruptedSegmenter

    kind = node.get("kind")
    settings = {k: v for k, v in node.items() if k not in NODE_KEYS}
    build = dict(settings)
    if untrusted and build.get("trust_checkpoint"):
        build["trust_checkpoint"] = False
    segmenter = SEGMENTERS.build(kind, build, where="segmenter")
    key_settings = {"kind": kind, **settings}
    key_settings.pop("device", None)  # the frames' key already holds the device
    if corrupt is not None and corrupt.active:
        segmenter = CorruptedSegmenter(segmenter, corrupt)
        key_settings.update(segmenter.settings())
    if check:
        segmenter.check()
    weights = {f: digest_file(f) for f in segmenter.weight_files()}
    return SegmenterRun(segmenter, key_settings, weights)


@dataclass(frozen=True)
class MasksInputs:
    frames: Output[Frames]
    prompt: Prompt
    trajectory_gt: list[np.ndarray] | None  # read by the oracle only
    segmenter: SegmenterRun
    feedback: FeedbackInputs | None  # None: consensus feedback off
    advice: FeedbackInputs | None  # what the fused-label advice renders with (None: not asked)


def label_count(num_labels: int, masks: list[np.ndarray]) -> int:
    """Labels to vote over: the dataset's count, or more where a segmenter's ids go beyond it."""
    return max(num_labels, 1 + max((int(m.max()) for m in masks), default=0))


@dataclass(frozen=True)
class VoteInputs:
    masks: Output[SegmentationResult]
    gaussians: Gaussians  # on `device`
    cameras: list[Camera]  # the trajectory the masks belong to
    num_labels: int  # the dataset's (the masks may add more)
    config: VoteConfig
    rule_version: str  # the vote rule plug-in's (core.plugins.Plugin.version)
    backend: str  # the vote backend that runs: native | triton | gsplat | torch
    kernel: str  # render.backends.implementation_digest(backend)
    device: str


@dataclass(frozen=True)
class RefineInputs:
    frames: Output[Frames]
    masks: Output[SegmentationResult]
    vote: Output[VoteResult]
    config: RefineConfig
    backend: str
    device: str


FRAMES = Stage("frames", 5, FramesInputs)  # 5: the renderer's source digest in the key
MASKS = Stage("masks", 6, MasksInputs)  # 6: streamed, their order kept in info["order"]
VOTE = Stage("vote", 4, VoteInputs)  # 4: labels -1 for unlabelled, no `labelled`
REFINE = Stage("refine", 3, RefineInputs)  # trained in the background: stage_two
STAGES = (FRAMES, MASKS, VOTE, REFINE)  # in graph order: each reads only those before it
STAGE_VERSIONS = {s.name: s.version for s in STAGES}


def stage_keys(
    config, gaussians: Gaussians, cameras, plan, frames_out: Output, prompt: Prompt, device
) -> tuple[MasksInputs, str, str]:
    """Stage I's masks' inputs and key, and the vote's key, for a `StageOneConfig`, its
    backend `plan` and the frames' output (the vote's key digests the masks' key, not their
    values: both are known before anything is segmented)."""
    c, s = config, config.settings
    feedback = advice = None
    if s.feedback.enabled:
        feedback = FeedbackInputs(
            s.feedback,
            c.vote,
            gaussians,
            list(cameras),
            c.num_labels,
            s.label_render.min_weight,
            plan.vote,
        )
    after = c.segmenter.segmenter.wants_advice
    if after is not None:  # the segmenter reads the fused labels: its masks depend on them
        advice = advice_inputs(
            after, c.vote, gaussians, cameras, c.num_labels, s.label_render.min_weight, plan.vote
        )
    masks_in = MasksInputs(frames_out, prompt, c.trajectory_gt, c.segmenter, feedback, advice)
    masks_key = MASKS.key(masks_in)
    vote_in = VoteInputs(
        Output(masks_key, None),
        gaussians,
        list(cameras),
        c.num_labels,
        c.vote,
        VOTE_RULES[c.vote.method].version,
        plan.vote,
        implementation_digest(plan.vote),
        device,
    )
    return masks_in, masks_key, VOTE.key(vote_in)
