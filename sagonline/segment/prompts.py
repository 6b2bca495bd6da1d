"""What to segment: prompts on one frame of the video, made by datasets, read by segmenters.

Clicks (positive/negative per object), boxes, masks, text, or nothing (automatic). Label 0 is
background; objects are 1..K in the order of `Prompt.objects`.
"""

from __future__ import annotations

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
    (label i+1 is texts[i]); no objects and no texts means automatic segmentation. `names`:
    the labels' names, background first, where the prompt's maker knows them (they name the
    outputs; the masks do not depend on them, so the digest leaves them out)."""

    frame: int = 0
    objects: list[ObjectPrompt] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)
    names: list[str] = field(default_factory=list)

    @property
    def num_labels(self) -> int:
        ids = [o.label for o in self.objects] + list(range(1, len(self.texts) + 1))
        return max(ids, default=0) + 1

    def digest(self) -> str:
        """Content digest of the prompt (frame, texts, every object's clicks, box and mask)."""
        from sagonline.core.provenance import digest_arrays, digest_json

        objects = [
            [o.label, o.text, digest_arrays([o.points, o.point_labels, o.box, o.mask])]
            for o in self.objects
        ]
        return digest_json(self.frame, list(self.texts), objects)


__all__ = ["ObjectPrompt", "Prompt"]
