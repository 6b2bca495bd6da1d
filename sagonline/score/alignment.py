"""How far a view's fitted object lies from where its mask says: the shift that aligns them.

A view whose object is rendered displaced (an error in that camera's pose, or a fit that put the
object elsewhere) loses IoU however well the vote labels it. For each scored view the diagnosis
(`score.diagnosis`) compares the fitted objects' silhouette (alpha >= 0.5 of each object rendered
alone) with the ground truth's object pixels at every whole-pixel shift up to `MAX_SHIFT` of the
view's larger side (FFT cross-correlation), and records the best shift and the silhouette IoU at
it and at none. A view is `displaced` where that shift is at least `DISPLACED_SHIFT` of the
larger side and raises the silhouette IoU by at least `DISPLACED_GAIN`.
"""

from __future__ import annotations

import math

import numpy as np

MAX_SHIFT = 0.15  # the shifts searched, as a share of the view's larger side
DISPLACED_SHIFT = 0.02  # a shift of at least this share of the larger side ...
DISPLACED_GAIN = 0.1  # ... that raises the silhouette IoU by at least this much: displaced
SHIFT_KEYS = ("shift_dx", "shift_dy", "silhouette_iou", "shifted_iou")  # a view's best_shift


def best_shift(truth: np.ndarray, silhouette: np.ndarray) -> dict[str, float | int]:
    """truth, silhouette: (H, W) bool. The whole-pixel shift (`shift_dx`, `shift_dy`: move the
    silhouette right and down by these) of largest IoU with `truth`, the nearest of equals;
    `silhouette_iou` unshifted and `shifted_iou` at it. {} where either mask is empty."""
    t, s = truth.astype(np.float64), silhouette.astype(np.float64)
    t_px, s_px = float(t.sum()), float(s.sum())
    if not t_px or not s_px:
        return {}
    h, w = t.shape
    reach = math.ceil(MAX_SHIFT * max(h, w))
    size = (h + reach, w + reach)  # zero padding: a shift within reach never wraps round
    corr = np.fft.irfft2(np.fft.rfft2(t, size) * np.conj(np.fft.rfft2(s, size)), size)
    dy, dx = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    overlap = np.maximum(np.rint(corr[dy % size[0], dx % size[1]]), 0)  # [2r+1, 2r+1] in common
    iou = overlap / (t_px + s_px - overlap)
    best = np.lexsort(((dy**2 + dx**2).ravel(), -iou.ravel()))[0]
    return {
        "shift_dx": int(dx.flat[best]),
        "shift_dy": int(dy.flat[best]),
        "silhouette_iou": round(float(iou[reach, reach]), 4),
        "shifted_iou": round(float(iou.flat[best]), 4),
    }


def displaced(row: dict, width: int, height: int) -> bool:
    """Whether a view's `best_shift` row says its object is rendered displaced."""
    if "shift_dx" not in row:
        return False
    shift = math.hypot(row["shift_dx"], row["shift_dy"])
    gain = row["shifted_iou"] - row["silhouette_iou"]
    return shift >= DISPLACED_SHIFT * max(width, height) and gain >= DISPLACED_GAIN


__all__ = [
    "DISPLACED_GAIN",
    "DISPLACED_SHIFT",
    "MAX_SHIFT",
    "SHIFT_KEYS",
    "best_shift",
    "displaced",
]
