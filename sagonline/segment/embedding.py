"""A SAM-family encoder's output for one frame (`Embedding`: the feature grid prompts are matched
against, and what else the decoder reads), and a mask's cells on that grid (`grid_cells`). Their
disk cache is `embedding_cache.EmbeddingCache`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from sagonline.segment.mask_geometry import box_of

SIZE = 1024  # the encoder's input side
GRID = 64  # the embedding's side (16 px cells of the 1024 frame)
CELL = SIZE // GRID  # a cell's side in the 1024 frame
CACHE_FORMAT = 1  # bumped when an entry's layout changes


def all_finite(array: np.ndarray) -> bool:
    """Whether every value is finite; float16 by its exponent bits (all ones, the largest they
    can be: inf or NaN), in one pass and a fraction of the time of `np.isfinite`, which widens
    each value first."""
    if array.dtype == np.float16:
        return array.size == 0 or int((array.view(np.uint16) & 0x7C00).max()) < 0x7C00
    return bool(np.isfinite(array).all())


def converted(array: np.ndarray, dtype) -> np.ndarray:
    """A float array, C-contiguous, in `dtype` (float16 or float32), by PyTorch: the same
    round-to-nearest-even values as numpy's `astype` (`tests/segment/test_sam_host.py`),
    in a tenth of its time for float32 -> float16 and a third for the way back."""
    array = np.ascontiguousarray(array)
    if array.dtype == dtype:
        return array
    import torch

    return torch.from_numpy(array).to(getattr(torch, np.dtype(dtype).name)).numpy()


def widened(array: np.ndarray) -> np.ndarray:
    """A float array as float32 (exact from float16)."""
    return converted(array, np.float32)


@dataclass
class Embedding:
    """One frame's encoder output.

    features: (256, 64, 64) float32, the image embedding (what prompts are matched against);
    stored_extras: the other arrays the decoder reads, by name, (C, H, W) as they are kept
    (SAM 2's high-resolution features, float16); `extras` has them as the decoder reads them;
    scale: (sx, sy), image pixels to the 1024 frame; size: the image's (height, width);
    cover: the (height, width) of the 1024 frame the image fills (the rest is padding)."""

    features: np.ndarray
    scale: tuple[float, float]
    size: tuple[int, int]
    cover: tuple[int, int]
    stored_extras: dict[str, np.ndarray] = field(default_factory=dict)
    _derived: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def extras(self) -> dict[str, np.ndarray]:  # name -> [1, C, H, W] float32
        """The decoder's other inputs in float32, widened once, when a decoder on the host
        first reads them (a decoder on the GPU gets the encoder's own outputs instead)."""
        if "extras" not in self._derived:
            self._derived["extras"] = {k: widened(v)[None] for k, v in self.stored_extras.items()}
        return self._derived["extras"]

    def grid_mask(self, mask: np.ndarray) -> np.ndarray:  # [64, 64] bool
        """An (H, W) mask on the 64x64 grid of the features (`grid_cells`)."""
        return grid_cells(mask, self.cover)

    def valid(self) -> np.ndarray:  # [64, 64] bool, read-only: the cells the image covers
        return covered_cells(tuple(self.size), tuple(self.cover))

    def normalized(self) -> np.ndarray:  # [64, 64, 256], computed once
        if "normalized" not in self._derived:
            f = self.features.transpose(1, 2, 0)
            self._derived["normalized"] = f / np.maximum(
                np.linalg.norm(f, axis=2, keepdims=True), 1e-6
            )
        return self._derived["normalized"]

    def _by_cell(self) -> tuple[np.ndarray, np.ndarray]:  # [C, 64*64], [64*64], computed once
        """The features with a column a cell (a view of `features`, no copy) and each cell's
        1 / norm: what the similarities and the mean features read, in place of `normalized`,
        whose (64, 64, C) layout strides a cell's values 16 KB apart."""
        if "by_cell" not in self._derived:
            flat = self.features.reshape(len(self.features), -1)
            norms = np.sqrt(np.einsum("cn,cn->n", flat, flat))  # no (C, 64*64) square made
            inverse = 1.0 / np.maximum(norms, 1e-6)
            self._derived["by_cell"] = (flat, inverse.astype(np.float32))
        return self._derived["by_cell"]

    def similarity(self, unit: np.ndarray) -> np.ndarray:  # [C] -> [64, 64]
        """Each cell's cosine similarity to a unit feature: `normalized() @ unit` in 0.20 ms
        against 0.54 for a view's first call (`bench.speed.sam_host`, this project's CPU)."""
        flat, inverse = self._by_cell()
        return ((unit.astype(np.float32) @ flat) * inverse).reshape(GRID, GRID)

    def mean_feature(
        self,
        mask: np.ndarray,  # [H, W] bool
        cells: np.ndarray | None = None,  # [64, 64] bool, its `grid_mask` where known
    ) -> np.ndarray | None:  # [256] unit, or None
        """The mean of the normalised features in the mask's cells, made unit (None where it
        covers none): one product of the features with each cell's weight (1 / its norm in
        the mask, 0 elsewhere), not a gather of `normalized`'s strided cells (0.07 ms against
        0.15 for a mask a fifth of the view across, later in a view: `bench.speed.sam_host`)."""
        cells = self.grid_mask(mask) if cells is None else cells
        count = np.count_nonzero(cells)
        if not count:
            return None
        flat, inverse = self._by_cell()
        mean = flat @ np.where(cells.ravel(), inverse, np.float32(0)) / np.float32(count)
        norm = float(np.linalg.norm(mean))
        return mean / norm if np.isfinite(norm) and norm > 1e-6 else None

    def cell_centre(self, index: int) -> np.ndarray:  # [2] x, y image pixels
        gy, gx = divmod(index, GRID)
        return np.array([(gx + 0.5) * 16 / self.scale[0], (gy + 0.5) * 16 / self.scale[1]])

    def to_frame(self, xy: np.ndarray) -> np.ndarray:  # [..., 2] image pixels -> 1024 frame
        return np.asarray(xy, np.float32) * np.asarray(self.scale, np.float32)


TIE = 4e-6  # a cell's share within this of a half is a tie, and a tie is not "mostly inside"


def grid_cells(
    mask: np.ndarray,  # [H, W] bool (or float)
    cover: tuple[int, int],
) -> np.ndarray:  # [64, 64] bool
    """A mask on the 64x64 grid of the features (a cell: mostly inside): each cell's share of
    the mask at the (height, width) `cover` it fills in the 1024 frame (the rest is padding).

    The shares are those of OpenCV's area resize of the mask to its cover, then of each 16x16
    cell's mean (`cell_operator`): one axis's operator, the mask's box, the other's; a fifth of
    the time of the two resizes for a mask a fifth of a 960x540 view across
    (`bench.speed.sam_host`). The two resizes decided an exact half by float32 rounding
    (0.5 out, 0.50000006 in); here a share within `TIE` of a half is out
    (`tests/segment/test_mask_geometry.py`: every other cell as the resizes have it)."""
    cells = np.zeros((GRID, GRID), bool)
    box = box_of(mask)
    if box is None:
        return cells
    x0, y0, x1, y1 = box.astype(int)
    direct = tuple(cover) == (SIZE, SIZE)  # the image fills the frame: straight to the grid
    down = cell_operator(mask.shape[0], cover[0], direct)[:, y0:y1]
    across = cell_operator(mask.shape[1], cover[1], direct)[:, x0:x1]
    (r0, r1), (c0, c1) = reached(down), reached(across)  # the cells the box reaches
    shares = (down[r0:r1] @ mask[y0:y1, x0:x1].astype(np.float32)) @ across[c0:c1].T
    cells[r0:r1, c0:c1] = shares > 0.5 + TIE
    return cells


def reached(operator: np.ndarray) -> tuple[int, int]:  # [64, n]: first, end of its cells
    """The first and the end of the cells that pixels of `operator` reach."""
    hit = np.flatnonzero(operator.any(axis=1))
    return int(hit[0]), int(hit[-1]) + 1


@functools.lru_cache(maxsize=16)
def cell_operator(pixels: int, cover: int, direct: bool) -> np.ndarray:  # [64, pixels] float32
    """Each grid cell's share of each of an axis's `pixels`: OpenCV's area resize of the axis
    to the `cover` pixels it fills in the 1024 frame, then each cell's mean of 16 (the frame's
    padding adds nothing); `direct`: resized straight to the 64 cells. Taken from the resize's
    own response to each pixel, 512 pixels at a time."""
    size = GRID if direct else cover
    response = np.empty((size, pixels))
    for start in range(0, pixels, 512):
        stop = min(start + 512, pixels)
        impulses = np.zeros((pixels, stop - start), np.float32)
        impulses[np.arange(start, stop), np.arange(stop - start)] = 1
        response[:, start:stop] = cv2.resize(
            impulses, (stop - start, size), interpolation=cv2.INTER_AREA
        )
    if not direct:
        padded = np.zeros((GRID * CELL, pixels))
        padded[:cover] = response
        response = padded.reshape(GRID, CELL, pixels).mean(axis=1)
    return response.astype(np.float32)


@functools.lru_cache(maxsize=16)
def covered_cells(size: tuple[int, int], cover: tuple[int, int]) -> np.ndarray:  # [64, 64] bool
    """The cells an image of (height, width) `size` covers: one grid a geometry, not one a
    view (read-only, shared)."""
    cells = grid_cells(np.ones(size, np.float32), cover)
    cells.flags.writeable = False
    return cells
