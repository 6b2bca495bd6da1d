"""The plug-in interface every 2D video segmenter implements (prompts: `sagonline.segment.prompts`).

A segmenter watches a video (the rendered trajectory) and answers one label map per frame.
Prompts say what to segment: clicks (positive/negative per object), boxes, masks, text, or
nothing (automatic). Label 0 is background; objects are 1..K in the order of `Prompt.objects`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sagonline.core.store import stored
from sagonline.segment.prompts import Prompt

# The segmenter of a scene of one's own when none is named (`sagonline segment`, `sagonline view`,
# `segment_scene`, the viewer's session): the weight-free classical one.
DEFAULT_SEGMENTER = "classical"


def label_map(mask: np.ndarray) -> np.ndarray:  # [H, W] uint8, uint16 or int64
    """A segmenter's answer (H, W) at the narrowest width that holds its ids: uint8 for ids in
    [0, 255] (a byte a pixel: 0.5 MB of a 960x540 view, not 4.1 MB of int64), uint16 up to
    65535, int64 otherwise (a negative id stays, for the vote's check to name). Values as
    `np.asarray(mask, np.int64)` reads them."""
    m = np.asarray(mask)
    if m.dtype in (np.uint8, np.uint16):
        return m
    if m.dtype == np.bool_:
        return m.view(np.uint8)
    m = np.asarray(m, np.int64)
    if m.size == 0:
        return m.astype(np.uint8)
    low, high = int(m.min()), int(m.max())
    if low < 0 or high > 65535:
        return m
    return m.astype(np.uint8 if high <= 255 else np.uint16)


@stored
@dataclass
class SegmentationResult:
    """masks: T label maps (H, W), `label_map`'s width (uint8 for up to 256 labels; an entry
    cached before holds int64); seconds: wall time per frame; name: who made them;
    info: what else the run reports (e.g. the consensus feedback's restarts)."""

    masks: list[np.ndarray]
    seconds: list[float]
    name: str
    info: dict = field(default_factory=dict)

    @property
    def ms_per_frame(self) -> float:
        return 1000.0 * float(np.mean(self.seconds)) if self.seconds else 0.0


class VideoSegmenter(ABC):
    """Subclasses implement `_segment`; `segment` checks the output and times it."""

    name = "segmenter"
    reads: tuple[str, ...] = ("clicks", "boxes", "masks")
    """The prompts it reads: clicks / boxes / masks, text, ground_truth (the oracle), or none
    (it segments automatically); a command refuses a prompt its segmenter cannot read."""

    wants_advice: int | None = None
    """Views Stage I votes before it offers this segmenter the fused labels rendered into each
    next view (`stream(advice=...)`); None: it does not read them."""

    def prepare(self, frames: list[np.ndarray], progress=None) -> None:  # noqa: B027 (optional hook)
        """Do now what every prompt on these frames would do first (a model's image
        embeddings): a viewer calls it in the background once its views are rendered, so a
        click costs only what depends on the click. `progress(done, total)`, when given, is
        called after each frame; it returns False to stop early (a segmenter replaced)."""

    def describe(self) -> dict:
        """What a run's results name of it besides its settings (its weights' SHA-256, say)."""
        return {}

    @property
    def version(self) -> str:
        """What produced its answers, for the masks' cache key: its package's version and a
        digest of its module's source (`core.plugins.module_version`)."""
        from sagonline.core.plugins import module_version

        return module_version(type(self).__module__)

    def weight_files(self) -> list[str]:
        """Local files the segmenter's answers depend on (checkpoints); their digests join the
        masks stage's cache key and the run's recorded inputs."""
        return []

    def weights_record(self) -> list[dict]:
        """Which weights ran: each file of `weight_files` there is, its path and sha256 (what
        labels.json records, and a replay compares)."""
        from sagonline.core.provenance import sha256_file

        return [
            {"path": str(Path(f).resolve()), "sha256": sha256_file(Path(f))}
            for f in self.weight_files()
            if Path(f).is_file()
        ]

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
        return SegmentationResult([label_map(m) for m in masks], seconds, self.name)

    def stream(
        self,
        frames: list[np.ndarray],
        prompt: Prompt,
        *,
        ground_truth: list[np.ndarray] | None = None,
        advice=None,
    ) -> Iterator[tuple[int, np.ndarray, float]]:  # (frame, [H, W] `label_map`, seconds)
        """The masks one by one as they are made, the prompt frame's first, each with the
        seconds it took (Stage I votes each as it comes). Segmenters that propagate frame by
        frame override `_stream`; the others answer the whole video first. `ground_truth` is
        read only by the oracle; `advice(t)`, for a segmenter that asks for it
        (`wants_advice`), is the fused labels rendered into view t, or None."""
        if not frames:
            raise ValueError(f"{self.name}: no frames to segment")
        if not 0 <= prompt.frame < len(frames):
            raise ValueError(
                f"{self.name}: prompt frame {prompt.frame} is outside the {len(frames)}-frame video"
            )
        seen: set[int] = set()
        start = time.perf_counter()
        made = (
            self._stream(frames, prompt, ground_truth)
            if advice is None
            else self._stream(frames, prompt, ground_truth, advice)
        )
        for item in made:
            i, mask = item[0], item[1]
            seconds = item[2] if len(item) > 2 else time.perf_counter() - start
            if not 0 <= i < len(frames) or i in seen:
                raise RuntimeError(f"{self.name}: answered frame {i} twice or out of range")
            if mask.shape != frames[i].shape[:2]:
                raise RuntimeError(
                    f"{self.name}: mask {i} is {mask.shape}, frame is {frames[i].shape[:2]}"
                )
            seen.add(i)
            yield i, label_map(mask), float(seconds)
            start = time.perf_counter()
        if len(seen) != len(frames):
            raise RuntimeError(f"{self.name}: answered {len(seen)} of {len(frames)} frames")

    def _stream(self, frames, prompt, ground_truth, advice=None) -> Iterator[tuple]:
        """(frame, mask[, seconds]) in the order made: here, the whole video first (`advice`
        is passed only to a segmenter that asks for it)."""
        start = time.perf_counter()
        masks, seconds = self._segment(frames, prompt, ground_truth)
        if seconds is None:
            seconds = [(time.perf_counter() - start) / len(frames)] * len(frames)
        if len(masks) != len(frames):
            raise RuntimeError(f"{self.name}: returned {len(masks)} masks for {len(frames)} frames")
        order = [prompt.frame, *(i for i in range(len(frames)) if i != prompt.frame)]
        for i in order:
            yield i, masks[i], seconds[i]

    @abstractmethod
    def _segment(
        self, frames, prompt, ground_truth
    ) -> tuple[list[np.ndarray], list[float] | None]: ...


def default_segmenter() -> VideoSegmenter:
    """`DEFAULT_SEGMENTER` built from the registry with its defaults."""
    from sagonline.core.plugins import SEGMENTERS

    return SEGMENTERS.build(DEFAULT_SEGMENTER, {})
