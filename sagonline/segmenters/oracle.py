"""The oracle: ground-truth masks of the rendered frames, optionally corrupted like a real model.

Corruptions (all seeded, applied in this order per frame):
- boundary: each object's mask eroded or dilated by up to `boundary_px` px (sign per frame);
- flicker: with probability `flicker`, a frame's object is replaced by its neighbour label
  (a wrong id for the whole frame, as trackers do when they lose an object);
- swap: with probability `swap`, two object ids trade places in the frame;
- blobs: with probability `blob_rate`, a false-positive ellipse of a random object id;
- drop: with probability `drop`, the frame comes back empty (all background).
"""

from __future__ import annotations

import cv2
import numpy as np

from sagonline.prompts import Prompt
from sagonline.segmenters.base import VideoSegmenter


class OracleSegmenter(VideoSegmenter):
    name = "oracle"

    def __init__(
        self,
        boundary_px: int = 0,
        flicker: float = 0.0,
        swap: float = 0.0,
        blob_rate: float = 0.0,
        blob_radius: float = 0.08,
        drop: float = 0.0,
        seed: int = 0,
    ):
        for name, p in (
            ("flicker", flicker),
            ("swap", swap),
            ("blob_rate", blob_rate),
            ("drop", drop),
        ):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"oracle {name} must be a probability, got {p}")
        self.boundary_px, self.flicker, self.swap = int(boundary_px), flicker, swap
        self.blob_rate, self.blob_radius, self.drop, self.seed = blob_rate, blob_radius, drop, seed

    @property
    def corrupted(self) -> bool:
        return bool(self.boundary_px or self.flicker or self.swap or self.blob_rate or self.drop)

    def _segment(self, frames, prompt: Prompt, ground_truth):
        if ground_truth is None:
            raise ValueError(
                "the oracle segmenter needs the frames' ground truth; this dataset "
                "has none for its trajectory"
            )
        rng = np.random.default_rng(self.seed)
        num_labels = max(prompt.num_labels, max(int(g.max()) for g in ground_truth) + 1)
        return [self.corrupt(np.asarray(g), num_labels, rng) for g in ground_truth], None

    def corrupt(self, gt: np.ndarray, num_labels: int, rng: np.random.Generator) -> np.ndarray:
        mask = gt.astype(np.int64).copy()
        objects = [int(v) for v in np.unique(mask) if v != 0]
        if self.boundary_px:
            k = int(rng.integers(1, self.boundary_px + 1))
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
            grow = rng.random() < 0.5
            out = np.zeros_like(mask) if not grow else mask.copy()
            for obj in objects:
                m = (mask == obj).astype(np.uint8)
                if grow:
                    out[(cv2.dilate(m, kernel) > 0) & (out == 0)] = obj
                else:
                    out[cv2.erode(m, kernel) > 0] = obj
            mask = out
        if objects and rng.random() < self.flicker:
            victim = int(rng.choice(objects))
            other = victim % (num_labels - 1) + 1 if num_labels > 2 else 0
            mask[mask == victim] = other
        if len(objects) >= 2 and rng.random() < self.swap:
            a, b = rng.choice(objects, size=2, replace=False)
            ma, mb = mask == a, mask == b
            mask[ma], mask[mb] = b, a
        if num_labels > 1 and rng.random() < self.blob_rate:
            h, w = mask.shape
            r = max(2, int(self.blob_radius * min(h, w)))
            center = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            blob = np.zeros((h, w), np.uint8)
            cv2.ellipse(blob, center, (r, int(r * 0.7)), float(rng.uniform(0, 180)), 0, 360, 1, -1)
            mask[blob > 0] = int(rng.integers(1, num_labels))
        if rng.random() < self.drop:
            mask[:] = 0
        return mask
