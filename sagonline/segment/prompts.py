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


def add_to_prompt(
    prompt: Prompt,
    frame: int,
    *,
    points=None,  # [P, 2] x, y pixels
    point_labels=None,  # [P] 1 positive, 0 negative (default: all positive)
    box=None,  # [4] x0, y0, x1, y1
    mask=None,  # [H, W] bool
    text: str | None = None,
    obj_id: int | None = None,
    name: str | None = None,
) -> tuple[Prompt, int]:
    """A new prompt: `prompt` with clicks, a box, a mask or a text added for one object on
    `frame`, and that object's label. A new object (labelled next, named `name`) unless
    `obj_id` names one, whose clicks are added to; every object is on one frame (refused
    otherwise: the segmenters take their prompt on one view). `prompt` is not changed."""
    from copy import deepcopy

    from sagonline.core.errors import PromptError

    if (prompt.objects or prompt.texts) and frame != prompt.frame:
        raise PromptError(
            f"the prompt is on view {prompt.frame}; add to it there (the segmenters take their "
            "prompt on one view), or start a new prompt"
        )
    objects, names = deepcopy(prompt.objects), list(prompt.names) or ["background"]
    if text is not None:
        texts = [*prompt.texts, text]
        return Prompt(frame, objects, texts, [*names, text]), len(texts)
    target = next((o for o in objects if o.label == obj_id), None)
    if target is None:
        if obj_id is not None:
            raise PromptError(f"no object {obj_id} in the prompt to add to")
        target = ObjectPrompt(max((o.label for o in objects), default=0) + 1)
        objects.append(target)
        names += [name or f"object_{target.label}"] if len(names) <= target.label else []
    if points is not None:
        points = np.asarray(points, np.float64).reshape(-1, 2)
        kinds = np.ones(len(points), np.int64) if point_labels is None else point_labels
        kinds = np.asarray(kinds, np.int64).reshape(-1)
        if len(kinds) != len(points):
            raise PromptError(f"{len(points)} clicks but {len(kinds)} click labels")
        have = target.points if target.points is not None else np.zeros((0, 2))
        had = target.point_labels if target.point_labels is not None else np.zeros(0, np.int64)
        target.points = np.concatenate([have, points])
        target.point_labels = np.concatenate([had, kinds]).astype(np.int64)
    if box is not None:
        target.box = np.asarray(box, np.float64).reshape(4)
    if mask is not None:
        target.mask = np.asarray(mask, bool)
    return Prompt(frame, objects, list(prompt.texts), names), target.label


__all__ = ["ObjectPrompt", "Prompt", "add_to_prompt"]
