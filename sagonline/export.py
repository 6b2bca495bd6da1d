"""Take a segmentation with you: per-Gaussian labels as files any 3DGS tool reads.

`write_segmentation` writes, into a folder that appears whole or not at all:
- labels.npy: (N,) int64, -1 for unlabelled Gaussians, else the label (0 background);
- labels.json: label names, counts, settings, the inputs' digests, timings;
- scene_labelled.ply: the input scene with a `label` vertex property added;
- objects/<name>.ply: only that object's Gaussians, with every property of the input (same
  names and dtypes: any 3DGS viewer and the harness load it); scene_without_<name>.ply: the rest;
- views/<i>_<view>_rgb.png and _labels.png (label ids as a grey PNG) of each trajectory view;
- recording.rrd (rerun), where asked for.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from sagonline.gaussians import Gaussians
from sagonline.io import write_ply
from sagonline.utils import atomic_write_image, atomic_write_json, atomic_write_npy


class OutputExists(FileExistsError):
    """The output folder is there already; nothing was written."""


def safe_name(name: str) -> str:
    """A label name as a file name: letters, digits, '-', '_' and '.', nothing else."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "label"


def vertex_table(gaussians: Gaussians, source: Path | None, tmp: Path) -> np.ndarray:
    """The scene's PLY vertex rows: the source file's own (every property, as stored) when it is
    a PLY holding one row per Gaussian, else the harness's 3DGS/2DGS layout of `gaussians`."""
    if source is None or source.suffix.lower() != ".ply":
        source = write_ply(tmp / "scene.ply", gaussians)
    data = PlyData.read(str(source))["vertex"].data
    if len(data) != len(gaussians):
        raise ValueError(
            f"{source}: {len(data)} vertices for {len(gaussians)} Gaussians (rows dropped on "
            "reading?): cannot carry its properties over"
        )
    return data


def _write_vertices(path: Path, rows: np.ndarray) -> None:
    PlyData([PlyElement.describe(rows, "vertex")], byte_order="<").write(str(path))


def write_segmentation(
    out: str | Path,
    gaussians: Gaussians,
    labels: np.ndarray,
    names: list[str],
    *,
    source: Path | None = None,
    info: dict | None = None,
    views: list[tuple[str, np.ndarray, np.ndarray]] | None = None,
    record: Callable[[Path], None] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the files of the module docstring into `out`. labels: (N,) int64 (-1:
    unlabelled); names: background first; views: (name, RGB uint8 (H, W, 3), (H, W) labels);
    record(path) writes the rerun recording. The folder is built beside `out` and renamed into
    place: an interrupted write leaves no half folder, and an existing `out` is replaced only
    with `overwrite` (OutputExists otherwise)."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise OutputExists(f"{out} exists; pass --overwrite to replace it")
    labels = np.asarray(labels, np.int64)
    if labels.shape != (len(gaussians),):
        raise ValueError(f"labels has shape {labels.shape}, expected ({len(gaussians)},)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "objects").mkdir(parents=True)
    try:
        rows = vertex_table(gaussians, source, tmp)
        (tmp / "scene.ply").unlink(missing_ok=True)
        counts = _write_ply_files(tmp, rows, labels, names)
        atomic_write_npy(tmp / "labels.npy", labels)
        atomic_write_json(tmp / "labels.json", {"names": names, "counts": counts, **(info or {})})
        for i, (name, rgb, lab) in enumerate(views or []):
            stem = f"{i:04d}_{safe_name(name)}"
            atomic_write_image(tmp / "views" / f"{stem}_rgb.png", rgb)
            ids = lab.astype(np.uint8 if len(names) < 256 else np.uint16)
            atomic_write_image(tmp / "views" / f"{stem}_labels.png", ids)
        if record is not None:
            record(tmp / "recording.rrd")
        _replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _write_ply_files(tmp: Path, rows: np.ndarray, labels: np.ndarray, names: list[str]) -> dict:
    """scene_labelled.ply, objects/<name>.ply, scene_without_<name>.ply; label counts."""
    labelled = np.empty(len(rows), dtype=rows.dtype.descr + [("label", "<i4")])
    for name in rows.dtype.names:
        labelled[name] = rows[name]
    labelled["label"] = labels
    _write_vertices(tmp / "scene_labelled.ply", labelled)
    counts = {"unlabelled": int((labels < 0).sum())}
    for k, name in enumerate(names):
        inside = labels == k
        counts[name] = int(inside.sum())
        if k == 0:
            continue
        file = safe_name(name)
        _write_vertices(tmp / "objects" / f"{file}.ply", rows[inside])
        _write_vertices(tmp / f"scene_without_{file}.ply", rows[~inside])
    return counts


def _replace(tmp: Path, out: Path) -> None:
    """Rename the finished folder into place (the old one, if any, is removed after)."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        out.rename(old)
    tmp.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def read_labels(folder: str | Path) -> tuple[np.ndarray, dict]:
    """labels.npy and labels.json of a written segmentation."""
    folder = Path(folder)
    info = json.loads((folder / "labels.json").read_text())
    return np.load(folder / "labels.npy", allow_pickle=False), info
