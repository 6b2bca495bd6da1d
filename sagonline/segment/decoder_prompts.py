"""A SAM-family decoder's prompts as its inputs and its answers: one prompt's points, box and
previous logits as the feeds both formats share, and several prompts of one view stacked into
one decoder call where their inputs agree in shape (`SamPair.decode_many`,
`segmenter.batch_prompts`).

Both decoders take a prompt axis first in `point_coords`, `point_labels` and `mask_input`, and
answer each prompt's row from it alone: the view's embedding is repeated per prompt inside the
graph. `has_mask_input` (one value) and SAM's `orig_im_size` hold for the whole call, so prompts
go together only where those agree too."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from sagonline.segment.embedding import Embedding

LOW_RES = 256  # the decoder's mask side
PER_PROMPT = ("point_coords", "point_labels", "mask_input")  # the inputs with a prompt axis


@dataclass
class Answer:
    """One mask the decoder proposes: (H, W) bool at the image's size, its (256, 256) logits
    (a later prompt's `mask_input`) and the decoder's own estimate of its IoU."""

    mask: np.ndarray
    logits: np.ndarray
    predicted_iou: float


class EnlargedAnswer(Answer):
    """SAM 2's answer, whose mask is its logits (of the 1024 frame, which the image fills)
    enlarged to the image, bilinear, then > 0: made when first read (following an object
    reads one of a prompt's three levels)."""

    def __init__(
        self,
        logits: np.ndarray,  # [256, 256] of the 1024 frame
        predicted_iou: float,
        size: tuple[int, int],  # the image's (height, width)
    ):
        self.logits, self.predicted_iou, self.size = logits, predicted_iou, size

    @functools.cached_property
    def mask(self) -> np.ndarray:  # type: ignore[override]  # [H, W] bool
        h, w = self.size
        return cv2.resize(self.logits, (w, h), interpolation=cv2.INTER_LINEAR) > 0.0


@dataclass(frozen=True)
class DecoderPrompt:
    """One prompt of a view: clicks, a box, and a previous answer's logits."""

    points: np.ndarray | None = None  # [P, 2] x, y image pixels
    labels: np.ndarray | None = None  # [P] 1 positive, 0 negative
    box: np.ndarray | None = None  # [4] x0, y0, x1, y1 image pixels
    logits: np.ndarray | None = None  # [256, 256] a previous answer's logits


def prompt_arrays(
    prompt: DecoderPrompt,
) -> tuple[np.ndarray, np.ndarray]:  # [P, 2] float32, [P] float32
    """Points and box corners as coordinates and SAM point labels (1, 0; 2, 3 the box's
    corners)."""
    coords, kinds = [], []
    if prompt.points is not None and len(prompt.points):
        coords += list(np.asarray(prompt.points, np.float32).reshape(-1, 2))
        kinds += list(np.asarray(prompt.labels, np.float32).reshape(-1))
    if prompt.box is not None:
        box = np.asarray(prompt.box, np.float32).reshape(4)
        coords += [box[:2], box[2:]]
        kinds += [2.0, 3.0]
    return np.asarray(coords, np.float32).reshape(-1, 2), np.asarray(kinds, np.float32)


def prompt_feeds(
    emb: Embedding,
    coords: np.ndarray,  # [P, 2] image pixels
    kinds: np.ndarray,  # [P] SAM point labels
    logits: np.ndarray | None,  # [256, 256] or None
) -> dict[str, np.ndarray]:
    """The decoder inputs both formats share, each with a prompt axis of one: the points in
    the 1024 frame, their labels, and a previous answer's logits (or none)."""
    has_mask = logits is not None
    mask = logits if has_mask else np.zeros((LOW_RES, LOW_RES), np.float32)
    return {
        "point_coords": emb.to_frame(coords)[None],
        "point_labels": kinds[None],
        "mask_input": mask[None, None].astype(np.float32),
        "has_mask_input": np.array([1.0 if has_mask else 0.0], np.float32),
    }


def calls(feeds: list[dict[str, np.ndarray]], together: bool) -> list[list[int]]:
    """Which prompts (by index) the decoder answers in one call: each alone, or (`together`)
    all whose per-prompt inputs agree in shape and whose other inputs agree in value; calls in
    the order of their first prompt."""
    if not together:
        return [[i] for i in range(len(feeds))]
    groups: dict[tuple, list[int]] = {}
    for i, feed in enumerate(feeds):
        key = tuple(
            (name, value.shape if name in PER_PROMPT else value.tobytes())
            for name, value in sorted(feed.items())
        )
        groups.setdefault(key, []).append(i)
    return list(groups.values())


def stacked(feeds: list[dict[str, np.ndarray]], rows: int | None = None) -> dict[str, np.ndarray]:
    """One call's inputs for prompts of one `calls` group: the per-prompt inputs concatenated
    along their prompt axis, the others as the first prompt's; `rows` (>= the prompts): the
    last prompt repeated to that many, whose answers the caller leaves unread."""
    rows = rows or len(feeds)
    if rows == 1:
        return feeds[0]
    padded = feeds + [feeds[-1]] * (rows - len(feeds))
    return {
        name: np.concatenate([f[name] for f in padded]) if name in PER_PROMPT else value
        for name, value in feeds[0].items()
    }


def rows_for(prompts: int, padded: bool) -> int:
    """A call's rows for `prompts` prompts: as many, or (`padded`) the next power of two, so
    that a decoder replayed as CUDA graphs (one a shape, `segmenter.cuda_graphs`) meets a few
    shapes however many objects a view follows."""
    return 1 << (prompts - 1).bit_length() if padded else prompts
