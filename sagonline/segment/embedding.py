"""A SAM-family encoder's output for one frame (`Embedding`: the feature grid prompts are matched
against, and what else the decoder reads) and the disk cache of them (`EmbeddingCache`).

A disk entry records what it was computed from (the frame's digest, the encoder's sha256, each
array's shape and dtype) inside a file whose bytes are digested (`core.store`); an entry that
does not match is named in a warning, removed and computed again, never used. A folder that
cannot hold the cache is named once and the run goes on without it. The folder is bounded:
past its size the least recently used entries go.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

SIZE = 1024  # the encoder's input side
GRID = 64  # the embedding's side (16 px cells of the 1024 frame)
CELL = SIZE // GRID  # a cell's side in the 1024 frame
CACHE_FORMAT = 1  # bumped when an entry's layout changes


def all_finite(array: np.ndarray) -> bool:
    """Whether every value is finite; float16 by its exponent bits (all ones: inf or NaN), a
    tenth of the time of `np.isfinite`, which widens each value first."""
    if array.dtype == np.float16:
        return not ((array.view(np.uint16) & 0x7C00) == 0x7C00).any()
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

    def mean_feature(
        self,
        mask: np.ndarray,  # [H, W] bool
        cells: np.ndarray | None = None,  # [64, 64] bool, its `grid_mask` where known
    ) -> np.ndarray | None:  # [256] unit, or None
        """The mean of the normalised features in the mask's cells, made unit (None where it
        covers none)."""
        cells = self.grid_mask(mask) if cells is None else cells
        if not cells.any():
            return None
        mean = self.normalized()[cells].mean(axis=0)
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
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows):
        return cells
    y0, y1 = rows[0], rows[-1] + 1
    cols = np.flatnonzero(mask[y0:y1].any(axis=0))
    x0, x1 = cols[0], cols[-1] + 1
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


class EmbeddingCache:
    """Embeddings on disk under `folder`, one verified `core.store` file a frame, at most
    `max_bytes` of them (None: unbounded): past it the entries least recently used (their
    modification time, renewed on each read) are removed down to `TRIM_TO` of the bound."""

    TRIM_TO = 0.8  # of max_bytes, so one trim makes room for many entries

    def __init__(self, folder: Path | None, max_bytes: int | None = None):
        self.folder = folder
        self.max_bytes = max_bytes
        self._used: int | None = None  # bytes under folder, counted at the first save
        self._warned = False

    def path(self, key: str) -> Path | None:
        return None if self.folder is None else self.folder / f"{key}.store"

    def load(self, key: str, expected: dict) -> dict[str, np.ndarray] | None:
        """The arrays stored under `key` when the entry records exactly `expected` (frame and
        encoder digests, names, shapes, dtypes) and every value is finite; else None, and a
        bad entry is named, removed and left to be computed again."""
        from sagonline.core import store

        path = self.path(key)
        if path is None or not os.path.lexists(path):
            return None
        reason = None
        if path.is_dir() or not path.is_file():
            reason = "not a file"
        else:
            try:
                entry = store.load(path)
            except FileNotFoundError:  # another process trimmed it meanwhile
                return None
            except (store.StoreError, OSError) as exc:
                reason = str(exc)
            else:
                reason = self._mismatch(entry, expected)
                if reason is None:
                    self._touch(path)
                    return {k: np.array(v) for k, v in entry["arrays"].items()}
        warnings.warn(
            f"embedding cache entry unusable, removed and recomputed: {path}: {reason}",
            stacklevel=3,
        )
        self._remove(path)
        return None

    @staticmethod
    def _mismatch(entry, expected: dict) -> str | None:
        if not isinstance(entry, dict) or not isinstance(entry.get("arrays"), dict):
            return "holds no embedding record"
        record = {k: entry.get(k) for k in ("format", "frame", "encoder")}
        want = {k: expected[k] for k in ("format", "frame", "encoder")}
        if record != want:
            return f"computed from {record}, not {want}"
        arrays = entry["arrays"]
        shapes = {
            k: [list(np.shape(v)), str(getattr(v, "dtype", type(v).__name__))]
            for k, v in arrays.items()
        }
        if shapes != expected["arrays"]:
            return f"arrays {shapes}, expected {expected['arrays']}"
        for name, value in arrays.items():
            if not all_finite(np.asarray(value)):
                return f"{name} holds values that are not finite"
        return None

    def save(self, key: str, record: dict, arrays: dict[str, np.ndarray]) -> None:
        from sagonline.core import store

        path = self.path(key)
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if self.max_bytes is not None and self._used is None:
                self._used = sum(size for _, size, _ in self._entries())
            store.save(path, {**record, "arrays": arrays})
        except OSError as exc:
            self._give_up(exc)
            return
        if self.max_bytes is None:
            return
        self._used += path.stat().st_size
        if self._used > self.max_bytes:
            self.trim(keep=path)

    def trim(self, keep: Path | None = None) -> int:
        """Remove the least recently used entries until the folder holds at most `TRIM_TO` x
        `max_bytes` (never `keep`, the entry just written); returns how many went."""
        entries = sorted(self._entries(), key=lambda e: e[2])  # oldest use first
        used = sum(size for _, size, _ in entries)
        target, removed = self.TRIM_TO * self.max_bytes, 0
        for path, size, _ in entries:
            if used <= target:
                break
            if path == keep:
                continue
            path.unlink(missing_ok=True)
            used, removed = used - size, removed + 1
        self._used = used
        return removed

    def _entries(self) -> list[tuple[Path, int, float]]:
        """(path, bytes, last use) of every entry file under the folder."""
        found = []
        for path in self.folder.glob("*.store"):
            try:
                st = path.stat()
            except FileNotFoundError:  # trimmed by another process meanwhile
                continue
            found.append((path, st.st_size, st.st_mtime))
        return found

    @staticmethod
    def _touch(path: Path) -> None:
        """Mark an entry used now (the trim removes the least recently used first)."""
        with contextlib.suppress(OSError):  # a read-only cache still serves its entries
            os.utime(path)

    def _remove(self, path: Path) -> None:
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
        except OSError as exc:
            self._give_up(exc)

    def _give_up(self, exc: OSError) -> None:
        """The folder cannot hold the cache: say so once, then go on without it."""
        if not self._warned:
            warnings.warn(
                f"embedding cache {self.folder} is unusable ({exc.strerror or exc}); embeddings "
                "are computed and kept in this process only",
                stacklevel=4,
            )
        self._warned = True
        self.folder = None
