"""Small geometry on (H, W) bool masks that the prompted segmenters share: overlap, box,
interior point, a disc around a click, the region of like colour a click lies in, Otsu's
threshold of a similarity map."""

from __future__ import annotations

import cv2
import numpy as np


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1))


def box_of(mask: np.ndarray) -> np.ndarray | None:  # [4] x0, y0, x1, y1
    """The box of the mask's pixels (end exclusive), or None for an empty mask: from the rows
    and columns holding any (a twentieth of the time of listing every pixel)."""
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows):
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return np.array([cols[0], rows[0], cols[-1] + 1, rows[-1] + 1], np.float32)


def interior_point(mask: np.ndarray) -> np.ndarray | None:  # [2] x, y: farthest from the edge
    """The mask's pixel farthest from its edge (the first in row order where several are), or
    None for an empty mask. The distances are taken within the mask's box and a ring of one
    pixel around it (inside the image; cv2 takes none beyond the image's edge): a pixel off the
    mask outside it lies no nearer to any inside than its clamp onto the ring, which is off the
    mask too, so the distances are the whole image's, in a fraction of its time."""
    box = box_of(mask)
    if box is None:
        return None
    x0, y0, x1, y1 = box.astype(int)
    top, left = max(y0 - 1, 0), max(x0 - 1, 0)
    ring = mask[top : y1 + 1, left : x1 + 1]  # slicing stops at the image's edge
    dist = cv2.distanceTransform(ring.astype(np.uint8), cv2.DIST_L2, 5)
    y, x = np.unravel_index(int(dist.argmax()), dist.shape)
    return np.array([left + x + 0.5, top + y + 0.5], np.float32)


def disc(size: tuple[int, int], xy, radius: int = 8) -> np.ndarray:  # [H, W] bool
    out = np.zeros(size, np.uint8)
    cv2.circle(out, (int(xy[0]), int(xy[1])), radius, 1, -1)
    return out > 0


def like_colour(
    frame: np.ndarray,  # [H, W, 3] uint8
    points: np.ndarray,  # [P, 2] x, y
    labels: np.ndarray,  # [P] 1 positive, 0 negative
    colour: np.ndarray | None = None,  # [H, W, 3] the frame's, where already made
) -> np.ndarray:  # [H, W] bool
    """The pixels of like colour connected to the positive clicks, less those of the negative
    ones (`classical.click_region`): what the clicks point at, by colour alone."""
    from sagonline.segment.classical import chromaticity_and_brightness, click_region

    colour = chromaticity_and_brightness(frame) if colour is None else colour
    region = np.zeros(frame.shape[:2], bool)
    for (x, y), kind in zip(np.asarray(points), np.asarray(labels), strict=True):
        if kind > 0:
            region |= click_region(colour, (int(x), int(y)))
    for (x, y), kind in zip(np.asarray(points), np.asarray(labels), strict=True):
        if kind <= 0:
            region &= ~click_region(colour, (int(x), int(y)))
    return region


def otsu(values: np.ndarray) -> float:
    """Otsu's threshold of values in [-1, 1] (cosine similarities)."""
    hist, edges = np.histogram(values, bins=64, range=(-1.0, 1.0))
    centres = (edges[:-1] + edges[1:]) / 2
    weight = np.cumsum(hist)
    total = weight[-1]
    mean = np.cumsum(hist * centres)
    between = (mean[-1] * weight - mean * total) ** 2 / np.maximum(weight * (total - weight), 1)
    return float(centres[int(between.argmax())])
