"""The oracle: ground-truth masks of the rendered frames, optionally corrupted like a real model
(the rules: `sagonline.segment.corruption`)."""

from __future__ import annotations

from sagonline.core.plugins import SEGMENTERS
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.corruption import MaskCorruption
from sagonline.segment.prompts import Prompt


@SEGMENTERS.register("oracle", MaskCorruption)
class OracleSegmenter(VideoSegmenter):
    """Ground-truth masks of the rendered frames, optionally corrupted (ablations)."""

    name = "oracle"
    reads = ("ground_truth",)

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
        try:
            self.corruption = MaskCorruption(
                boundary_px, flicker, swap, blob_rate, blob_radius, drop, seed
            )
        except ValueError as exc:
            raise ValueError(f"oracle {str(exc).removeprefix('corruption ')}") from None

    def _segment(self, frames, prompt: Prompt, ground_truth):
        if ground_truth is None:
            raise ValueError(
                "the oracle segmenter needs the frames' ground truth; this dataset "
                "has none for its trajectory"
            )
        num_labels = max(prompt.num_labels, max(int(g.max()) for g in ground_truth) + 1)
        return self.corruption.apply(ground_truth, num_labels), None
