"""What Stage I's engine (`stage_one.StageOne`) streams, and what it hands on when done."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sagonline.core.progress import Progress
from sagonline.pipeline.graph import Output, StageRun
from sagonline.pipeline.stages import Frames
from sagonline.render.backends import BackendPlan
from sagonline.segment.base import SegmentationResult
from sagonline.vote.consensus import VoteResult


@dataclass(frozen=True)
class FrameRendered:
    """Frame `index` of the trajectory, RGB uint8 (H, W, 3)."""

    index: int
    image: np.ndarray
    cached: bool = False


@dataclass(frozen=True)
class MaskReady:
    """The mask frame `index` votes with ((H, W) label ids, `segment.base.label_map`'s width) and
    the segmenter's seconds."""

    index: int
    mask: np.ndarray
    seconds: float
    cached: bool = False


@dataclass(frozen=True)
class ViewVoted:
    """Frame `index` voted: `voted` of the `total` voting frames so far."""

    index: int
    voted: int
    total: int


@dataclass(frozen=True)
class LabelsUpdated:
    """Labels per Gaussian from the votes so far: (N,) int64, -1 unlabelled, 0 background,
    1.. the objects; `final` once every voting frame has voted."""

    labels: np.ndarray
    voted: int
    total: int
    final: bool = False


Event = FrameRendered | MaskReady | ViewVoted | LabelsUpdated


@dataclass
class StageOneOutput:
    """What Stage I hands on (to scoring, Stage II, `segment` and `export`): the stages'
    outputs (with their keys), what each stage did (`computed` or `cached`, and seconds), the
    label count, the names of the views whose masks voted and the backends each stage used."""

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
        return self.vote.value.labels.cpu().numpy()

    @property
    def keys(self) -> dict[str, str]:
        return {"frames": self.frames.key, "masks": self.masks.key, "vote": self.vote.key}


class StageOneBars:
    """Stage I's stream on two bars of `n` views each: `<prefix>render` counts FrameRendered
    and, from the first MaskReady on, `<prefix>segment and vote` counts the masks."""

    def __init__(self, n: int, prefix: str = "", enabled: bool = True):
        self.n, self.prefix, self.enabled = n, prefix, enabled
        self.frames = Progress(f"{prefix}render", n, enabled=enabled)
        self.masks: Progress | None = None

    def update(self, event) -> None:
        """Count `event` (any event of the stream; only renders and masks are counted)."""
        if isinstance(event, FrameRendered):
            self.frames.update()
        elif isinstance(event, MaskReady):
            if self.masks is None:
                self.frames.close()
                self.masks = Progress(
                    f"{self.prefix}segment and vote", self.n, enabled=self.enabled
                )
            self.masks.update()

    def close(self) -> None:
        self.frames.close()
        if self.masks is not None:
            self.masks.close()
