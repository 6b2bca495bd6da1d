"""How an NVOS task is prompted, one function per protocol the field uses.

- `scribbles`, sampling `uniform`: up to n seeded points drawn uniformly from each scribble file
  (this harness's first protocol);
- `scribbles`, sampling `skeleton`: SAGA's: each scribble is skeletonised and a skeleton pixel is
  kept where a seeded uniform value exceeds 0.98 (positive) or 0.995 (negative scribbles);
- `click`: one positive scribble pixel (seeded), one click per task;
- `points`: a frozen JSON file of click points, as SAGA v2 and GARfVDB publish them:
  {"<task>": [[x, y], ...], "_scale": 4, "_comment": "..."}, points at the original
  resolution, `_scale` the factor from the released (4x-downsampled) masks to it. Never shipped
  and never downloaded: pass its path (`dataset.adapter.points_file=...`).

Points come back in the pixel coordinates of the view they prompt (pixel centres at +0.5).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sagonline.core.errors import DatasetError

SKELETON_KEEP = {1: 0.98, 0: 0.995}  # SAGA: keep a skeleton pixel where uniform() > this


def uniform_points(mask: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
    """(P, 2) x, y of up to n distinct foreground pixels of mask (H, W), drawn uniformly."""
    ys, xs = np.nonzero(mask)
    pick = rng.choice(len(xs), size=min(n, len(xs)), replace=False)
    return np.stack([xs[pick], ys[pick]], 1).astype(np.float64)


def skeleton_points(mask: np.ndarray, rng: np.random.Generator, positive: bool) -> np.ndarray:
    """(P, 2) x, y of the skeleton pixels of mask (H, W) kept by SAGA's rule (at least one: the
    skeleton pixel of largest draw when the rule keeps none)."""
    from skimage.morphology import skeletonize

    ys, xs = np.nonzero(skeletonize(mask.astype(bool)))
    if len(xs) == 0:
        return np.zeros((0, 2))
    draw = rng.uniform(size=len(xs))
    keep = draw > SKELETON_KEEP[int(positive)]
    if not keep.any():
        keep[np.argmax(draw)] = True
    return np.stack([xs[keep], ys[keep]], 1).astype(np.float64)


def read_points_file(path: str | Path, tasks: list[str], known: list[str]) -> tuple[dict, float]:
    """{task: (P, 2) x, y at the original resolution} for `tasks`, and the file's `_scale`.
    Errors name the file and the task: unreadable JSON, an unknown task, a task missing, a point
    that is not two finite numbers."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"nvos: points file {path} not found (dataset.adapter.points_file)")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"nvos: points file {path} is not readable JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise DatasetError(f"nvos: points file {path} must hold an object: task -> [[x, y], ...]")
    unknown = sorted(k for k in data if not k.startswith("_") and k not in known)
    if unknown:
        raise DatasetError(f"nvos: points file {path}: unknown task(s) {unknown}; tasks: {known}")
    scale = data.get("_scale", 1)
    if not isinstance(scale, int | float) or not np.isfinite(scale) or scale <= 0:
        raise DatasetError(f"nvos: points file {path}: _scale must be a positive number")
    points = {}
    for task in tasks:
        if task not in data:
            raise DatasetError(f"nvos: points file {path} has no points for task {task!r}")
        try:
            pts = np.asarray(data[task], dtype=np.float64)
        except (TypeError, ValueError):
            pts = np.zeros((0, 3))
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0 or not np.isfinite(pts).all():
            raise DatasetError(
                f"nvos: points file {path}, task {task!r}: expected a non-empty list of [x, y] "
                f"numbers, got {str(data[task])[:80]}"
            )
        points[task] = pts
    return points, float(scale)


def check_inside(points: np.ndarray, width: int, height: int, where: str) -> None:
    """Every point (x, y) inside a width x height image, else an error naming `where`."""
    outside = (points[:, 0] < 0) | (points[:, 0] > width) | (points[:, 1] < 0)
    outside |= points[:, 1] > height
    if outside.any():
        x, y = points[np.argmax(outside)]
        raise DatasetError(
            f"{where}: point ({x:.1f}, {y:.1f}) lies outside the {width}x{height} image "
            f"({int(outside.sum())} of {len(points)} points do)"
        )
