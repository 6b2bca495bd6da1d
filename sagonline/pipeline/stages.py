"""The cached stages of one scene: frames -> masks -> vote, and the student's checkpoint.

Each stage is a function of one inputs dataclass (`graph.Stage`); its key digests every field,
so what a stage depends on is exactly what its inputs dataclass holds:
- frames: the scene, the trajectory cameras, the resolved renderer, the background, the device;
- masks: the frames (by their key), the prompt, the trajectory's ground truth (the oracle
  reads it), the segmenter (settings and weight digests) and, with consensus feedback on, what
  the feedback votes and renders with;
- vote: the masks (by their key), the scene, the cameras, the label count, the vote settings,
  the renderer and the device;
- refine: the frames, masks and vote (by their keys) and the student's settings: the key
  names the student's checkpoint (`stage_two`), which trains in the background.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from sagonline.core.provenance import digest_json
from sagonline.core.store import stored
from sagonline.pipeline.graph import Output, Stage
from sagonline.refine import RefineConfig
from sagonline.render.api import render, to_uint8
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import SegmentationResult, VideoSegmenter
from sagonline.segment.prompts import Prompt
from sagonline.vote.consensus import VoteConfig, VoteResult, consensus_vote
from sagonline.vote.feedback import FeedbackInputs, segment_with_feedback


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
    backend: str  # the resolved renderer: native | torch | gsplat
    background: tuple[float, float, float]
    device: str  # cpu | cuda


def render_frames(inputs: FramesInputs, progress: bool = False) -> Frames:
    bg = torch.tensor(inputs.background)
    images, start = [], time.perf_counter()
    for cam in tqdm(inputs.cameras, desc="render", leave=False, disable=not progress):
        images.append(
            to_uint8(render(inputs.gaussians, cam, background=bg, backend=inputs.backend).rgb)
        )
    return Frames(images, (time.perf_counter() - start) / max(len(images), 1))


@dataclass(frozen=True)
class SegmenterRun:
    """A segmenter with the settings it was built from and the digests of its weight files:
    what its masks depend on (the instance itself is not digested)."""

    segmenter: VideoSegmenter
    settings: dict = field(default_factory=dict)
    weights: dict[str, str] = field(default_factory=dict)  # path -> file digest

    def digest(self) -> str:
        return digest_json(self.segmenter.name, self.settings, sorted(self.weights.values()))


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


def segment_frames(inputs: MasksInputs, progress: bool = False) -> SegmentationResult:
    frames, fb = inputs.frames.value.images, inputs.feedback
    segmenter = inputs.segmenter.segmenter
    if fb is None:
        return segmenter.segment(frames, inputs.prompt, ground_truth=inputs.trajectory_gt)
    seg, _ = segment_with_feedback(segmenter, frames, inputs.prompt, fb, inputs.trajectory_gt)
    return seg


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
    backend: str
    device: str


def vote(inputs: VoteInputs, progress: bool = False) -> VoteResult:
    masks = inputs.masks.value.masks
    return consensus_vote(
        inputs.gaussians,
        inputs.cameras,
        masks,
        label_count(inputs.num_labels, masks),
        inputs.config,
        backend=inputs.backend,
        progress=progress,
    )


@dataclass(frozen=True)
class RefineInputs:
    frames: Output[Frames]
    masks: Output[SegmentationResult]
    vote: Output[VoteResult]
    config: RefineConfig
    backend: str
    device: str


FRAMES = Stage("frames", 4, FramesInputs, render_frames)
MASKS = Stage("masks", 5, MasksInputs, segment_frames)  # 5: corruption streams per kind
VOTE = Stage("vote", 3, VoteInputs, vote)
REFINE = Stage("refine", 3, RefineInputs, None)  # trained in the background: stage_two
STAGES = (FRAMES, MASKS, VOTE, REFINE)  # in graph order: each reads only those before it
STAGE_VERSIONS = {s.name: s.version for s in STAGES}
