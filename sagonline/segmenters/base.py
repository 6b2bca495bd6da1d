"""The plug-in interface every 2D video segmenter implements.

A segmenter watches a video (the rendered trajectory) and answers one label map per frame.
Prompts say what to segment: clicks (positive/negative per object), boxes, masks, text, or
nothing (automatic). Label 0 is background; objects are 1..K in the order of `Prompt.objects`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ObjectPrompt:
    """What marks one object on the prompt frame. points: (P, 2) x, y pixels; point_labels:
    (P,) 1 positive / 0 negative; box: (4,) x0, y0, x1, y1; mask: (H, W) bool."""

    label: int
    points: np.ndarray | None = None
    point_labels: np.ndarray | None = None
    box: np.ndarray | None = None
    mask: np.ndarray | None = None
    text: str | None = None


@dataclass
class Prompt:
    """Prompts on frame `frame` of the video; `texts` for open-vocabulary segmenters
    (label i+1 is texts[i]); no objects and no texts means automatic segmentation."""

    frame: int = 0
    objects: list[ObjectPrompt] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)

    @property
    def num_labels(self) -> int:
        ids = [o.label for o in self.objects] + list(range(1, len(self.texts) + 1))
        return max(ids, default=0) + 1

    def digest(self) -> str:
        """Content digest of the prompt (frame, texts, every object's clicks, box and mask)."""
        from sagonline.provenance import digest_arrays, digest_json

        objects = [
            [o.label, o.text, digest_arrays([o.points, o.point_labels, o.box, o.mask])]
            for o in self.objects
        ]
        return digest_json(self.frame, list(self.texts), objects)


@dataclass
class SegmentationResult:
    """masks: T label maps (H, W) int64; seconds: wall time per frame; name: who made them."""

    masks: list[np.ndarray]
    seconds: list[float]
    name: str

    @property
    def ms_per_frame(self) -> float:
        return 1000.0 * float(np.mean(self.seconds)) if self.seconds else 0.0


class VideoSegmenter(ABC):
    """Subclasses implement `_segment`; `segment` checks the output and times it."""

    name = "segmenter"

    def weight_files(self) -> list[str]:
        """Local files the segmenter's answers depend on (checkpoints); their digests join the
        masks stage's cache key and the run's recorded inputs."""
        return []

    def check(self) -> None:  # noqa: B027 (optional hook: most segmenters have nothing to check)
        """Fail fast, before anything is rendered: open and validate weights and settings.
        Raise ValueError naming the option and the file."""

    def segment(
        self,
        frames: list[np.ndarray],
        prompt: Prompt,
        *,
        ground_truth: list[np.ndarray] | None = None,
    ) -> SegmentationResult:
        """frames: T RGB uint8 (H, W, 3) images in video order. `ground_truth` is read only
        by the oracle."""
        if not frames:
            raise ValueError(f"{self.name}: no frames to segment")
        if not 0 <= prompt.frame < len(frames):
            raise ValueError(
                f"{self.name}: prompt frame {prompt.frame} is outside the {len(frames)}-frame video"
            )
        start = time.perf_counter()
        masks, seconds = self._segment(frames, prompt, ground_truth)
        total = time.perf_counter() - start
        if seconds is None:
            seconds = [total / len(frames)] * len(frames)
        if len(masks) != len(frames):
            raise RuntimeError(f"{self.name}: returned {len(masks)} masks for {len(frames)} frames")
        for i, (m, f) in enumerate(zip(masks, frames, strict=True)):
            if m.shape != f.shape[:2]:
                raise RuntimeError(f"{self.name}: mask {i} is {m.shape}, frame is {f.shape[:2]}")
        return SegmentationResult(
            [np.asarray(m, dtype=np.int64) for m in masks], seconds, self.name
        )

    @abstractmethod
    def _segment(
        self, frames, prompt, ground_truth
    ) -> tuple[list[np.ndarray], list[float] | None]: ...
