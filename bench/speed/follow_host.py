"""The host work of following objects into a view, each part as first written and as it is
now (the rows of format "follow" of `bench.speed.sam_host`, whose docstring lists them)."""

from __future__ import annotations

import functools

import cv2
import numpy as np

from bench.speed.render import timed
from sagonline.segment.embedding import GRID
from sagonline.segment.sam_onnx import SIZE, Sam1Pair, Sam2Pair


def first_shares(
    mask: np.ndarray,  # [H, W] bool
    cover: tuple[int, int],
) -> np.ndarray:  # [64, 64] float32
    """Each feature cell's share of the mask as first written: the mask resized to its cover
    of the 1024 frame, the frame padded, then resized to the grid (or straight to the grid
    where the image fills the frame); a cell is in above a half."""
    ch, cw = cover
    if (ch, cw) == (SIZE, SIZE):
        return cv2.resize(mask.astype(np.float32), (GRID, GRID), interpolation=cv2.INTER_AREA)
    big = np.zeros((SIZE, SIZE), np.float32)
    big[:ch, :cw] = cv2.resize(mask.astype(np.float32), (cw, ch), interpolation=cv2.INTER_AREA)
    return cv2.resize(big, (GRID, GRID), interpolation=cv2.INTER_AREA)


def first_interior_point(mask: np.ndarray) -> np.ndarray:  # [2] x, y
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    y, x = np.unravel_index(int(dist.argmax()), dist.shape)
    return np.array([x + 0.5, y + 0.5], np.float32)


def first_paint(found: dict, size) -> np.ndarray:  # [H, W] int64
    out = np.zeros(size, np.int64)
    for label, (mask, *_) in sorted(found.items()):
        out[mask] = label
    return out


def first_enlarged(ids: np.ndarray, height: int, width: int) -> np.ndarray:  # [H, W]
    rows = (np.arange(height) + 0.5) * ids.shape[0] // height
    cols = (np.arange(width) + 0.5) * ids.shape[1] // width
    return ids[np.ix_(rows.astype(int), cols.astype(int))]


def follow_rows(height: int, width: int, repeats: int) -> list[dict]:
    """Each part of following objects into a view, as first written and now."""
    from sagonline.segment.embedding import Embedding, grid_cells
    from sagonline.segment.mask_geometry import interior_point
    from sagonline.segment.sam_prompting import SamFamilySegmenter
    from sagonline.vote.feedback import ADVICE_SIDE, enlarged

    rng = np.random.default_rng(2)
    found = {}
    for label in range(1, 6):  # five objects, a fifth of the view's side across
        mask = np.zeros((height, width), np.uint8)
        centre = (int(rng.integers(width)), int(rng.integers(height)))
        cv2.circle(mask, centre, min(height, width) // 5, 1, -1)
        found[label] = (mask > 0, None)
    _, cover = Sam1Pair.geometry(Sam1Pair, height, width)
    emb = Embedding(np.zeros((1, 1, 1), np.float32), (1.0, 1.0), (height, width), cover)
    ones = np.ones((height, width), np.float32)
    logits = rng.standard_normal((3, 256, 256), np.float32)  # a SAM 2 prompt's three levels
    row = [logits, np.ones(3, np.float32)]

    def first_levels() -> np.ndarray:  # every level enlarged, one read
        return [cv2.resize(m, (width, height), interpolation=cv2.INTER_LINEAR) > 0 for m in logits][
            0
        ]

    features = rng.standard_normal((256, 64, 64), np.float32)  # a view's embedding
    cells, unit = grid_cells(found[1][0], cover), np.ones(256, np.float32) / 16
    read = Embedding(features, (1.0, 1.0), (height, width), cover)  # read once before: warm
    normalized = read.normalized()
    read.mean_feature(found[1][0], cells)

    def unit_mean(rows: np.ndarray) -> np.ndarray:  # [M, C] -> [C]
        mean = rows.mean(0)
        return mean / np.linalg.norm(mean)

    def first_normalized() -> np.ndarray:  # [64, 64, C], strided as `normalized` makes it
        f = features.transpose(1, 2, 0)
        return f / np.maximum(np.linalg.norm(f, axis=2, keepdims=True), 1e-6)

    def fresh(method: str, *args):  # on an embedding not yet read: its first call in a view
        return lambda: getattr(Embedding(features, (1.0, 1.0), (height, width), cover), method)(
            *args
        )

    scale = min(1.0, ADVICE_SIDE / max(height, width))  # the advice's render of the objects
    small_size = (max(1, round(width * scale)), max(1, round(height * scale)))
    painted = SamFamilySegmenter.paint(found, (height, width)).astype(np.int32)
    small = cv2.resize(painted, small_size, interpolation=cv2.INTER_NEAREST).astype(np.int64)
    pairs = {
        "advice enlarged to the view": (
            lambda: first_enlarged(small, height, width),
            lambda: enlarged(small, height, width),
        ),
        "interior point": (
            lambda: first_interior_point(found[1][0]),
            lambda: interior_point(found[1][0]),
        ),
        "grid cells of an object": (
            lambda: first_shares(found[1][0], cover) > 0.5,
            lambda: grid_cells(found[1][0], cover),
        ),
        "covered cells": (lambda: first_shares(ones, cover) > 0.5, emb.valid),
        "SAM 2 answer, one level of three read": (
            first_levels,
            lambda: Sam2Pair.answers(Sam2Pair, emb, row)[0].mask,
        ),
        "paint (5 objects)": (
            lambda: first_paint(found, (height, width)),
            lambda: SamFamilySegmenter.paint(found, (height, width)),
        ),
        "mean feature of an object, a view's first": (
            lambda: unit_mean(first_normalized()[cells]),  # the strided cells gathered
            fresh("mean_feature", found[1][0], cells),
        ),
        "mean feature of an object, later in a view": (
            lambda: unit_mean(normalized[cells]),
            lambda: read.mean_feature(found[1][0], cells),
        ),
        "similarity to an object, a view's first": (
            lambda: first_normalized() @ unit,
            fresh("similarity", unit),
        ),
    }
    rows = []
    for part, (first, now) in pairs.items():
        want = first()
        # the features' parts sum float32 in another order: the same to 1e-6
        close = "feature" in part or "similarity" in part
        same = functools.partial(np.allclose, rtol=0, atol=1e-6) if close else np.array_equal
        for when, make in (("as first written", first), ("now", now)):
            rows.append(
                {
                    "format": "follow",
                    "way": f"{part}, {when}",
                    "ms": 1000 * timed(make, repeats, "cpu"),
                    "MB_to_device": 0.0,
                    "same_as_first_written": bool(same(make(), want)),
                }
            )
    return rows
