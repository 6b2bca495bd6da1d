"""The per-candidate mask arithmetic of the SAM family's prompting (`mask_geometry.box_of`,
`iou`, `interior_point`, `Embedding.grid_mask`, `Embedding.valid`): each equal, value for
value, to its first, slower form, on masks of every kind (empty, full, one pixel, boxes at the
edges, noise, discs cut by the edges) and on image sizes whose cover of the 1024 frame ends
inside a cell, on a cell's edge, or fills the frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from bench.speed.follow_host import first_shares
from sagonline.segment.embedding import GRID, SIZE, Embedding
from sagonline.segment.mask_geometry import box_of, interior_point, iou

# (height, width): a view; 4:3; a cover ending inside a cell (577 rows); portrait; tiny;
# a line of pixels; larger than the frame; square (SAM 2's stretch fills the frame)
SHAPES = [(540, 960), (480, 640), (677, 1201), (1000, 750), (33, 17), (1, 7), (1600, 1200)]


def first_box_of(mask):
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return None
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32)


def first_iou(a, b):
    return float((a & b).sum() / max((a | b).sum(), 1))


def assert_cells_as_first(got, shares):
    """The cells of more than half as the first form has them, but for its ties: a share within
    a millionth of a half, which float32 rounding put in or out; a tie is out."""
    tie = np.abs(shares - 0.5) <= 1e-6
    np.testing.assert_array_equal(got[~tie], (shares > 0.5)[~tie])
    assert not got[tie].any()
    return int(tie.sum())


def first_interior_point(mask):
    """The distance transform of the whole image."""
    if not mask.any():
        return None
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    y, x = np.unravel_index(int(dist.argmax()), dist.shape)
    return np.array([x + 0.5, y + 0.5], np.float32)


def masks(shape, seed: int):
    """Empty, full, a pixel in each corner, boxes anywhere (edges included), and noise."""
    h, w = shape
    rng = np.random.default_rng(seed)
    yield np.zeros(shape, bool)
    yield np.ones(shape, bool)
    for y, x in ((0, 0), (h - 1, w - 1), (0, w - 1), (h - 1, 0)):
        one = np.zeros(shape, bool)
        one[y, x] = True
        yield one
    for _ in range(12):
        box = np.zeros(shape, bool)
        y0, x0 = rng.integers(0, h), rng.integers(0, w)
        box[y0 : y0 + rng.integers(1, h + 1), x0 : x0 + rng.integers(1, w + 1)] = True
        yield box
    for _ in range(4):
        yield rng.random(shape) < rng.random()
    for _ in range(6):  # discs, cut by the image's edges or not, and their unions
        disc = np.zeros(shape, np.uint8)
        for _ in range(rng.integers(1, 4)):
            centre = (
                int(rng.integers(-w // 4, w + w // 4)),
                int(rng.integers(-h // 4, h + h // 4)),
            )
            cv2.circle(disc, centre, int(rng.integers(1, max(h, w) // 2 + 2)), 1, -1)
        yield disc > 0


@pytest.mark.parametrize("shape", SHAPES, ids=str)
def test_box_overlap_and_interior_point_are_their_first_forms(shape):
    previous = None
    for mask in masks(shape, seed=sum(shape)):
        want, got = first_box_of(mask), box_of(mask)
        assert (want is None and got is None) or (
            got.dtype == np.float32 and np.array_equal(got, want)
        )
        if previous is not None:
            assert iou(mask, previous) == first_iou(mask, previous)
        previous = mask
        want, got = first_interior_point(mask), interior_point(mask)
        assert (want is None and got is None) or np.array_equal(got, want)


@pytest.mark.parametrize("stretch", [False, True], ids=["sam", "sam2"])
@pytest.mark.parametrize("shape", SHAPES, ids=str)
def test_the_grid_cells_are_those_of_the_whole_padded_frame(shape, stretch):
    h, w = shape
    if stretch:  # SAM 2: the image resized to fill the frame
        scale, cover = (SIZE / w, SIZE / h), (SIZE, SIZE)
    else:  # SAM: the longer side to 1024, padded right and bottom
        s = SIZE / max(h, w)
        scale, cover = (s, s), (round(h * s), round(w * s))
    emb = Embedding(np.zeros((1, 1, 1), np.float32), scale, shape, cover)
    ties = 0
    for mask in masks(shape, seed=h * w):
        got = emb.grid_mask(mask)
        assert got.shape == (GRID, GRID) and got.dtype == bool
        ties += assert_cells_as_first(got, first_shares(mask, emb.cover))
    if shape == (480, 640):  # 1.6 frame pixels an image pixel: boxes that halve cells
        assert ties
    valid = emb.valid()  # one grid a geometry, shared by its views
    assert_cells_as_first(valid, first_shares(np.ones(shape, bool), emb.cover))
    assert not valid.flags.writeable
    assert Embedding(np.zeros((1, 1, 1), np.float32), scale, shape, cover).valid() is valid
