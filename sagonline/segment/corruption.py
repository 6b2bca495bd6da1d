"""Masks corrupted like a real model's, for robustness studies of the vote.

`MaskCorruption` is what the oracle applies to the ground truth (`segmenter=oracle
segmenter.flicker=...`) and what `corrupt.*` applies to any segmenter's answers
(`CorruptedSegmenter`), so a real segmenter's masks can be degraded by the same rules.

Corruptions (all seeded, each kind from its own stream, applied in this order per frame):
- boundary: each object's mask eroded or dilated by up to `boundary_px` px (sign per frame);
- flicker: with probability `flicker`, a frame's object is replaced by its neighbour label
  (a wrong id for the whole frame, as trackers do when they lose an object; with one object
  the neighbour is the background, so the object vanishes from the frame);
- swap: with probability `swap`, two object ids trade places in the frame;
- blobs: with probability `blob_rate`, a false-positive ellipse of a random object id;
- drop: with probability `drop`, the frame comes back empty (all background).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import Prompt


@dataclass
class MaskCorruption:
    """How masks are corrupted (all off by default); `seed` seeds one stream per kind of
    corruption, run through the video."""

    boundary_px: int = 0
    """Each object's mask eroded or dilated by up to this many pixels (sign drawn per frame)."""
    flicker: float = 0.0
    """Probability that a frame's object takes its neighbour's label (or vanishes)."""
    swap: float = 0.0
    """Probability that two object ids trade places in a frame."""
    blob_rate: float = 0.0
    """Probability of a false-positive ellipse of a random object id in a frame."""
    blob_radius: float = 0.08
    """A blob's radius as a fraction of the frame's shorter side."""
    drop: float = 0.0
    """Probability that a frame comes back empty (all background)."""
    seed: int = 0
    """Seeds one stream per kind of corruption."""

    def __post_init__(self):
        from sagonline.core.settings import check_settings

        check_settings(
            "corruption",
            **{
                name: (0.0 <= getattr(self, name) <= 1.0, getattr(self, name), "a probability")
                for name in ("flicker", "swap", "blob_rate", "drop")
            },
            boundary_px=(0 <= self.boundary_px <= 256, self.boundary_px, "in [0, 256] pixels"),
            blob_radius=(0 < self.blob_radius <= 1, self.blob_radius, "in (0, 1]"),
        )
        self.boundary_px = int(self.boundary_px)

    @property
    def active(self) -> bool:
        return bool(self.boundary_px or self.flicker or self.swap or self.blob_rate or self.drop)

    def apply(self, masks: list[np.ndarray], num_labels: int) -> list[np.ndarray]:
        """masks: T label maps (H, W) in video order -> T corrupted int64 maps.

        Each kind of corruption draws from its own seeded stream, the same draws per frame
        whatever the settings: the frames that flicker at 0.1 also flicker at 0.3, and turning
        the boundary noise on does not change which frames flicker."""
        streams = [np.random.default_rng([self.seed, kind]) for kind in range(len(KINDS))]
        return [self.frame(np.asarray(m), num_labels, streams) for m in masks]

    def frame(self, gt: np.ndarray, num_labels: int, streams) -> np.ndarray:
        """One (H, W) label map corrupted (labels 0..num_labels-1); `streams`: one generator
        per kind of corruption, in the order of KINDS."""
        rng = dict(zip(KINDS, streams, strict=True))
        mask = gt.astype(np.int64).copy()
        objects = [int(v) for v in np.unique(mask) if v != 0]
        size, grow = int(rng["boundary"].integers(1, 1 << 16)), rng["boundary"].random() < 0.5
        if self.boundary_px:
            mask = _move_boundaries(mask, objects, 1 + size % self.boundary_px, grow)
        flicker, pick = rng["flicker"].random(), rng["flicker"].random()
        if objects and flicker < self.flicker:
            victim = objects[int(pick * len(objects))]
            other = victim % (num_labels - 1) + 1 if num_labels > 2 else 0
            mask[mask == victim] = other
        swap, first, step = rng["swap"].random(3)
        if len(objects) >= 2 and swap < self.swap:
            n = len(objects)
            i = int(first * n)
            a, b = objects[i], objects[(i + 1 + int(step * (n - 1))) % n]  # two different ids
            ma, mb = mask == a, mask == b
            mask[ma], mask[mb] = b, a
        blob = rng["blob"].random(size=5)
        if num_labels > 1 and blob[0] < self.blob_rate:
            mask = _add_blob(mask, blob[1:], self.blob_radius, num_labels)
        if rng["drop"].random() < self.drop:
            mask[:] = 0
        return mask


KINDS = ("boundary", "flicker", "swap", "blob", "drop")


def _add_blob(mask, u, radius, num_labels):
    """A false-positive ellipse; u: 4 uniforms (centre x, y, angle, label)."""
    h, w = mask.shape
    r = max(2, int(radius * min(h, w)))
    centre = (int(u[0] * w), int(u[1] * h))
    blob = np.zeros((h, w), np.uint8)
    cv2.ellipse(blob, centre, (r, int(r * 0.7)), float(u[2] * 180), 0, 360, 1, -1)
    out = mask.copy()
    out[blob > 0] = 1 + int(u[3] * (num_labels - 1))
    return out


def _move_boundaries(mask, objects, k, grow):
    """Every object eroded or (into the background) dilated by k px."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    out = np.zeros_like(mask) if not grow else mask.copy()
    for obj in objects:
        m = (mask == obj).astype(np.uint8)
        if grow:
            out[(cv2.dilate(m, kernel) > 0) & (out == 0)] = obj
        else:
            out[cv2.erode(m, kernel) > 0] = obj
    return out


class CorruptedSegmenter(VideoSegmenter):
    """Any segmenter whose answers pass through a `MaskCorruption` (`corrupt.*` in
    bench.runners.eval)."""

    def __init__(self, inner: VideoSegmenter, corruption: MaskCorruption):
        self.inner, self.corruption = inner, corruption
        self.name, self.reads = inner.name, inner.reads

    @property
    def version(self) -> str:
        return f"{self.inner.version};{super().version}"

    def weight_files(self) -> list[str]:
        return self.inner.weight_files()

    def check(self) -> None:
        self.inner.check()

    def settings(self) -> dict:
        """What the corruption adds to the segmenter's settings (and so to the masks' key)."""
        return {"corrupt": asdict(self.corruption)}

    def _segment(self, frames, prompt: Prompt, ground_truth):
        answer = self.inner.segment(frames, prompt, ground_truth=ground_truth)
        num_labels = max(prompt.num_labels, 1 + max(int(m.max()) for m in answer.masks))
        return self.corruption.apply(answer.masks, num_labels), answer.seconds
