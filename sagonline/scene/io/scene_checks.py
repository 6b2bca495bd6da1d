"""Checks every scene reader applies to the raw values of a file (PLY, .splat): finite values,
unit quaternions; a problem names the file, the property and the row."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from sagonline.core.errors import SceneFileError


def normalize_quats(path: Path, quats: np.ndarray, what: str, first_row: int = 0) -> np.ndarray:
    norm = np.linalg.norm(quats.astype(np.float64), axis=1)
    zero = norm < 1e-12
    if zero.any():
        rows = np.flatnonzero(zero)
        raise SceneFileError(
            f"{path}: {len(rows)} zero-norm quaternions in {what} "
            f"(first at row {first_row + rows[0]})"
        )
    # Rows already unit to float32 precision stay as they are, so a write/read cycle is exact.
    unit = np.abs(norm - 1.0) < 1e-6
    out = (quats.astype(np.float64) / norm[:, None]).astype(np.float32)
    out[unit] = quats[unit]
    return out


DROP_HINT = (
    "Pass drop_nonfinite=True (command line: --drop-nonfinite; eval and make scenes: "
    "dataset.adapter.drop_nonfinite=true) to drop them."
)


def nonfinite_rows(
    path: Path, bad: dict[str, list[int]], bad_rows: np.ndarray, drop: bool
) -> np.ndarray:
    """The rows to keep, or SceneFileError when dropping was not asked for. bad: property ->
    [rows, first row] of its non-finite (or overflowing) values."""
    prop, (count, row) = next(iter(bad.items()))
    total, n = int(bad_rows.sum()), len(bad_rows)
    if not drop:
        raise SceneFileError(
            f"{path}: property {prop!r} has NaN/Inf values or values that overflow float32 once "
            f"activated ({count} rows, first at row {row}); {total} of {n} rows are affected in "
            f"all. {DROP_HINT}"
        )
    if total == n:
        raise SceneFileError(f"{path}: every Gaussian has NaN/Inf or overflowing values")
    warnings.warn(f"{path}: dropped {total} of {n} Gaussians with NaN/Inf values", stacklevel=4)
    return ~bad_rows


def check_finite(
    path: Path, raw: dict[str, np.ndarray], names: dict[str, list[str]], drop: bool
) -> dict[str, np.ndarray]:
    """Rows of `raw` (key -> (N, C) arrays) with only finite values, or SceneFileError."""
    n = next(iter(raw.values())).shape[0]
    bad_rows = np.zeros(n, dtype=bool)
    bad: dict[str, list[int]] = {}
    for key, values in raw.items():
        hit = ~np.isfinite(values)
        for col in np.unique(np.nonzero(hit)[1]):
            rows = np.flatnonzero(hit[:, col])
            bad_rows[rows] = True
            name = names[key][min(col, len(names[key]) - 1)]
            entry = bad.setdefault(name, [0, int(rows[0])])
            entry[0] += len(rows)
    if not bad:
        return raw
    keep = nonfinite_rows(path, bad, bad_rows, drop)
    return {k: v[keep] for k, v in raw.items()}


def require_scene_file(path: Path) -> None:
    """SceneFileError naming `path` unless it is a regular file: missing, a folder, or a
    device or pipe (`/dev/null` was "not found")."""
    if path.is_file():
        return
    if not path.exists():
        why = "scene file not found"
    elif path.is_dir():
        why = "a folder, not a scene file (name the .ply or .splat in it)"
    else:
        why = "not a regular file (a device, a pipe or a socket), not a scene file"
    raise SceneFileError(f"{path}: {why}")
