"""Take a segmentation with you: per-Gaussian labels as files any 3DGS tool reads.

`write_segmentation` writes, into a folder that appears whole or not at all (`outputs`):
- labels.npy: (N,) int64, -1 for unlabelled Gaussians, else the label (0 background);
- labels.json: label names, counts, settings, the inputs' digests, timings;
- scene_labelled.ply: the input scene with a `label` vertex property added;
- objects/<name>.ply: only that object's Gaussians, with every property of the input (same
  names and dtypes: any 3DGS viewer and the harness load it); scene_without_<name>.ply: the rest;
- views/<i>_<view>_rgb.png, _labels.png (the label ids, raw, for scoring), _labels_color.png
  and _overlay.png (the labels in colour, and over the render) of each trajectory view;
- recording.rrd (rerun), where asked for;
- .sagonline-output.json, the manifest that lets `--overwrite` recognise the folder as ours.

Label names become file names: each is cleaned to letters (any script), digits, '-', '_' and
'.'; two names that clean to the same file (`chair`, `chair!`) are refused (or, for names a
dataset gave, suffixed and reported), and the names `background` and `unlabelled`, which
labels.json uses itself, are refused for objects.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from sagonline.core.files import atomic_write_image, atomic_write_json, atomic_write_npy
from sagonline.core.outputs import OutputError, output_folder
from sagonline.labels.colours import label_colors
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.io import write_ply

RESERVED_NAMES = ("background", "unlabelled")
# The most labels a segmentation may have: each object is written as two PLYs of the scene.
MAX_OBJECTS = int(os.environ.get("SAGONLINE_MAX_OBJECTS", 255))


class LabelNameError(ValueError):
    """Label names that cannot each have a file of their own; says which."""


def safe_name(name: str) -> str:
    """A label name as a file name: letters (any script), digits, '-', '_' and '.'."""
    return re.sub(r"[^\w.-]+", "_", name).strip("._") or "label"


def object_file_names(names: list[str], on_clash: str = "refuse") -> tuple[list[str], list[str]]:
    """The label names (background first) as written, and each object's file name. A name
    that cleans to another's file (compared without case, as some file systems do) or is
    reserved (labels.json counts `background` and `unlabelled` itself) is refused
    (LabelNameError), or with on_clash="suffix" renamed `<name>_2`, `_3`, ... with a warning."""
    if len(names) - 1 > MAX_OBJECTS:
        raise LabelNameError(
            f"{len(names) - 1} objects exceed the ceiling of {MAX_OBJECTS} "
            "(sagonline.labels.export.MAX_OBJECTS; SAGONLINE_MAX_OBJECTS raises it): each "
            "object is written as two PLYs of the scene"
        )
    kept, files = [names[0]], []
    taken: dict[str, str] = {n: n for n in RESERVED_NAMES}
    for name in names[1:]:
        file = safe_name(name)
        clash = taken.get(file.casefold()) or (
            name if name.strip().casefold() in RESERVED_NAMES else None
        )
        if clash is not None and on_clash != "suffix":
            if clash in RESERVED_NAMES or name.strip().casefold() in RESERVED_NAMES:
                raise LabelNameError(
                    f"object name {name!r} is reserved ({' and '.join(RESERVED_NAMES)} are "
                    "counted in labels.json); choose another"
                )
            raise LabelNameError(
                f"objects {clash!r} and {name!r} would both be written as objects/{file}.ply; "
                "give them names that differ in letters or digits"
            )
        new, n = name, 1
        while clash is not None:
            n += 1
            new, file = f"{name}_{n}", f"{safe_name(name)}_{n}"
            clash = taken.get(file.casefold())
        if new != name:
            warnings.warn(
                f"label {name!r} is written as {new!r} (objects/{file}.ply)", stacklevel=2
            )
        taken[file.casefold()] = new
        kept.append(new)
        files.append(file)
    return kept, files


def vertex_table(gaussians: Gaussians, source: Path | None, tmp: Path) -> np.ndarray:
    """The scene's PLY vertex rows: the source file's own (every property, as stored) when it is
    a PLY holding one row per Gaussian (less the rows a reader dropped for NaN/Inf), else the
    harness's 3DGS/2DGS layout of `gaussians`."""
    if source is None or source.suffix.lower() != ".ply":
        source = write_ply(tmp / "scene.ply", gaussians)
    data = PlyData.read(str(source))["vertex"].data
    if len(data) != len(gaussians):  # rows dropped on reading (NaN/Inf): the same rows here
        from sagonline.scene.io.ply import kept_rows

        keep = kept_rows(source)
        if int(keep.sum()) == len(gaussians):
            return data[keep]
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
    inputs: Iterable[str | Path] = (),
    command: str = "segment",
    on_clash: str = "refuse",
) -> Path:
    """Write the files of the module docstring into `out`. labels: (N,) int64 (-1:
    unlabelled); names: background first; views: (name, RGB uint8 (H, W, 3), (H, W) labels);
    record(path) writes the rerun recording; inputs: what the command read (`out` may not be
    or hold any of them). The folder is built beside `out` and swapped into place whole; an
    existing `out` is replaced only with `overwrite`, and only when the harness wrote it
    (OutputError otherwise)."""
    out = Path(out)
    labels = np.asarray(labels, np.int64)
    if labels.shape != (len(gaussians),):
        raise ValueError(f"labels has shape {labels.shape}, expected ({len(gaussians)},)")
    if labels.size and (labels.min() < -1 or labels.max() >= len(names)):
        raise ValueError(
            f"labels hold ids {int(labels.min())}..{int(labels.max())}; the names cover "
            f"-1..{len(names) - 1}"
        )
    names, files = object_file_names(names, on_clash=on_clash)
    inputs = [*inputs, *([source] if source is not None else [])]
    with output_folder(
        out, inputs=inputs, overwrite=overwrite, command=command, flag="--out"
    ) as tmp:
        (tmp / "objects").mkdir()
        rows = vertex_table(gaussians, source, tmp)
        (tmp / "scene.ply").unlink(missing_ok=True)
        counts = _write_ply_files(tmp, rows, labels, names, files)
        atomic_write_npy(tmp / "labels.npy", labels)
        record_info = {"names": names, "files": dict(zip(names[1:], files, strict=True))}
        atomic_write_json(tmp / "labels.json", record_info | {"counts": counts, **(info or {})})
        colours = label_colors(len(names))
        for i, (name, rgb, lab) in enumerate(views or []):
            stem = f"{i:04d}_{safe_name(name)}"
            atomic_write_image(tmp / "views" / f"{stem}_rgb.png", rgb)
            ids = lab.astype(np.uint8 if len(names) < 256 else np.uint16)
            atomic_write_image(tmp / "views" / f"{stem}_labels.png", ids)  # raw ids, to score
            atomic_write_image(tmp / "views" / f"{stem}_labels_color.png", colours[lab])
            atomic_write_image(tmp / "views" / f"{stem}_overlay.png", overlay(rgb, lab, colours))
        if record is not None:
            record(tmp / "recording.rrd")
    return out


def overlay(rgb: np.ndarray, labels: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the render with each object's pixels tinted by its colour (background
    left as it is)."""
    out = rgb.astype(np.float32)
    on = labels > 0
    out[on] = 0.45 * out[on] + 0.55 * colours[labels[on]]
    return out.clip(0, 255).astype(np.uint8)


def _write_ply_files(
    tmp: Path, rows: np.ndarray, labels: np.ndarray, names: list[str], files: list[str]
) -> dict:
    """scene_labelled.ply, objects/<file>.ply, scene_without_<file>.ply; label counts."""
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
        _write_vertices(tmp / "objects" / f"{files[k - 1]}.ply", rows[inside])
        _write_vertices(tmp / f"scene_without_{files[k - 1]}.ply", rows[~inside])
    return counts


def read_labels(folder: str | Path) -> tuple[np.ndarray, dict]:
    """labels.npy and labels.json of a written segmentation."""
    folder = Path(folder)
    info = json.loads((folder / "labels.json").read_text())
    return np.load(folder / "labels.npy", allow_pickle=False), info


__all__ = [
    "MAX_OBJECTS",
    "LabelNameError",
    "OutputError",
    "object_file_names",
    "read_labels",
    "safe_name",
    "write_segmentation",
]
