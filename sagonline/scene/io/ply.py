"""Read and write trained Gaussian scenes: 3DGS / 2DGS `point_cloud.ply` (`.splat`: splat.py).

Raw file values (opacity logit, log scales, unnormalised wxyz quaternions) exist only here; the
rest of the library sees activated `Gaussians`. Writing chooses, for every activated value, the
float32 raw value whose activation rounds back to it, so `read(write(g)) == g` bit for bit for
any scene that was read from a file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from sagonline.core.errors import SceneFileError
from sagonline.core.files import atomic_write
from sagonline.scene.gaussians import Gaussians, sh_degree_from_coeffs
from sagonline.scene.io.ply_rows import read_ply_header, vertex_blocks
from sagonline.scene.io.scene_checks import nonfinite_rows, normalize_quats, require_scene_file

_REQUIRED = [
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]


def read_scene(path: str | Path, *, drop_nonfinite: bool = False) -> Gaussians:
    """Read a `.ply` (3DGS or 2DGS layout) or `.splat` file into activated Gaussians."""
    path = Path(path)
    if path.suffix.lower() == ".splat":
        from sagonline.scene.io.splat import read_splat

        return read_splat(path, drop_nonfinite=drop_nonfinite)
    return read_ply(path, drop_nonfinite=drop_nonfinite)


def scene_file(path: str | Path) -> Path:
    """The scene file itself, or the point_cloud.ply inside a folder: the folder's own, its
    gaussians/ one, or the latest point_cloud/iteration_*/ one (a 3DGS output folder)."""
    path = Path(path)
    if not path.is_dir():
        return path
    for candidate in (path / "point_cloud.ply", path / "gaussians" / "point_cloud.ply"):
        if candidate.is_file():
            return candidate
    iterations = sorted(
        path.glob("point_cloud/iteration_*/point_cloud.ply"),
        key=lambda p: int("".join(filter(str.isdigit, p.parent.name)) or 0),
    )
    if iterations:
        return iterations[-1]
    raise SceneFileError(
        f"{path}: is a folder with no point_cloud.ply (looked in it, in gaussians/ and in "
        "point_cloud/iteration_*/); give the .ply or .splat file"
    )


def read_ply(path: str | Path, *, drop_nonfinite: bool = False) -> Gaussians:
    """Read the 3DGS (scale_0..2) or 2DGS (scale_0..1) `point_cloud.ply` layout.

    Binary files are streamed in blocks of rows straight into the activated arrays, so reading
    needs little more memory than the scene itself (the file's size, for the full layout).
    Values that are NaN/Inf, or that overflow float32 once activated (a log-scale above ~88.7
    or below ~-103), are refused naming the property and row, or dropped with `drop_nonfinite`.
    """
    return _read_arrays(Path(path)).finish(drop_nonfinite)


def kept_rows(path: str | Path) -> np.ndarray:
    """(rows,) bool: the PLY rows `read_ply(path, drop_nonfinite=True)` keeps (the others hold
    NaN/Inf or overflowing values); what carries a file's own properties over to them."""
    return ~_read_arrays(Path(path)).bad_rows


def _read_arrays(path: Path) -> _SceneArrays:
    require_scene_file(path)
    header = read_ply_header(path)
    vertex = next((e for e in header.elements if e.name == "vertex"), None)
    if vertex is None:
        raise SceneFileError(
            f"{path}: no 'vertex' element (found elements {[e.name for e in header.elements]}); "
            "a Gaussian PLY stores one vertex per Gaussian"
        )
    props = [name for name, _ in vertex.properties]
    missing = [p for p in _REQUIRED if p not in props]
    if missing:
        raise SceneFileError(
            f"{path}: missing required property {missing[0]!r} (all missing: {missing})"
        )
    if vertex.count == 0:
        raise SceneFileError(f"{path}: the vertex element is empty")
    rest_names = sorted((p for p in props if p.startswith("f_rest_")), key=lambda p: int(p[7:]))
    if len(rest_names) % 3:
        raise SceneFileError(
            f"{path}: {len(rest_names)} f_rest_* properties is not a multiple of 3"
        )
    try:
        sh_degree_from_coeffs(len(rest_names) // 3 + 1)
    except ValueError:
        raise SceneFileError(
            f"{path}: {len(rest_names)} f_rest_* properties does not match "
            "any SH degree 0-3 (expected 0, 9, 24 or 45)"
        ) from None
    layout = {
        "means": ["x", "y", "z"],
        "dc": ["f_dc_0", "f_dc_1", "f_dc_2"],
        "rest": rest_names,
        "opacity": ["opacity"],
        "scales": ["scale_0", "scale_1"] + (["scale_2"] if "scale_2" in props else []),
        "quats": ["rot_0", "rot_1", "rot_2", "rot_3"],
    }
    if all(n in props for n in ("nx", "ny", "nz")):
        layout["normals"] = ["nx", "ny", "nz"]
    blocks = vertex_blocks(path, header, vertex)  # checks the rows fit the file first
    scene = _SceneArrays(path, vertex.count, layout)
    for start, block in blocks:
        scene.fill(start, block)
    return scene


class _SceneArrays:
    """The activated arrays of a scene, filled block by block from raw PLY rows."""

    def __init__(self, path: Path, n: int, layout: dict[str, list[str]]):
        self.path, self.n, self.layout = path, n, layout
        k = len(layout["rest"]) // 3 + 1
        self.means = np.empty((n, 3), np.float32)
        self.sh = np.empty((n, k, 3), np.float32)
        self.opacities = np.empty(n, np.float32)
        self.scales = np.empty((n, len(layout["scales"])), np.float32)
        self.quats = np.empty((n, 4), np.float32)
        self.normals = np.empty((n, 3), np.float32) if "normals" in layout else None
        self.bad_rows = np.zeros(n, dtype=bool)
        self.bad: dict[str, list[int]] = {}  # property -> [rows, first row]

    def _columns(self, block: np.ndarray, key: str) -> np.ndarray:
        names = self.layout[key]
        out = np.empty((len(block), len(names)), np.float32)
        for i, name in enumerate(names):
            out[:, i] = block[name]
        return out

    def _flag(self, key: str, bad: np.ndarray, start: int) -> None:
        if not bad.any():
            return
        rows, cols = np.nonzero(bad)
        self.bad_rows[start + np.unique(rows)] = True
        for col in np.unique(cols):
            name = self.layout[key][col]
            hit = np.flatnonzero(bad[:, col])
            entry = self.bad.setdefault(name, [0, start + int(hit[0])])
            entry[0] += len(hit)

    def fill(self, start: int, block: np.ndarray) -> None:
        stop = start + len(block)
        raw = {key: self._columns(block, key) for key in self.layout}
        for key, values in raw.items():
            self._flag(key, ~np.isfinite(values), start)
        scales = _exp(raw["scales"])
        overflow = np.isfinite(raw["scales"]) & ~(np.isfinite(scales) & (scales > 0))
        self._flag("scales", overflow, start)
        self.means[start:stop] = raw["means"]
        self.sh[start:stop, 0] = raw["dc"]
        c, k = len(block), self.sh.shape[1]
        self.sh[start:stop, 1:] = raw["rest"].reshape(c, 3, k - 1).transpose(0, 2, 1)
        self.opacities[start:stop] = _sigmoid(raw["opacity"][:, 0])
        self.scales[start:stop] = scales
        self.quats[start:stop] = normalize_quats(self.path, raw["quats"], "rot_0..rot_3", start)
        if self.normals is not None:
            self.normals[start:stop] = raw["normals"]

    def finish(self, drop: bool) -> Gaussians:
        arrays = {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "sh": self.sh,
            "normals": self.normals,
        }
        if self.bad:
            keep = nonfinite_rows(self.path, self.bad, self.bad_rows, drop)
            arrays = {k: (v[keep] if v is not None else None) for k, v in arrays.items()}
        return Gaussians(
            **{k: torch.from_numpy(v) if v is not None else None for k, v in arrays.items()}
        )


def write_ply(path: str | Path, gaussians: Gaussians) -> Path:
    """Write the standard layout (2DGS when scales are (N, 2)); atomic: temp file then rename."""
    path = Path(path)
    g = gaussians.to("cpu")
    n = len(g)
    means = g.means.detach().numpy().astype(np.float32)
    sh = g.sh.detach().numpy().astype(np.float32)
    columns: list[tuple[str, np.ndarray]] = [(c, means[:, i]) for i, c in enumerate("xyz")]
    if g.normals is not None:
        normals = g.normals.detach().numpy().astype(np.float32)
        columns += [(c, normals[:, i]) for i, c in enumerate(["nx", "ny", "nz"])]
    columns += [(f"f_dc_{i}", sh[:, 0, i]) for i in range(3)]
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)
    columns += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    columns.append(("opacity", _encode(g.opacities.detach().numpy(), _sigmoid, _logit)))
    log_scales = _encode(g.scales.detach().numpy(), _exp, np.log)
    columns += [(f"scale_{i}", log_scales[:, i]) for i in range(log_scales.shape[1])]
    quats = g.quats.detach().numpy().astype(np.float32)
    columns += [(f"rot_{i}", quats[:, i]) for i in range(4)]

    record = np.empty(n, dtype=[(name, "f4") for name, _ in columns])
    for name, values in columns:
        record[name] = values
    data = PlyData([PlyElement.describe(record, "vertex")], byte_order="<")
    return atomic_write(path, lambda tmp: data.write(str(tmp)))


# --- raw <-> activated ------------------------------------------------------------------------


def _sigmoid(x: np.ndarray) -> np.ndarray:
    """1 / (1 + e^-x), exactly 0 or 1 where e^-x overflows (a logit of -1e30 is an opacity of
    0, said by nothing: it is a valid if extreme value)."""
    with np.errstate(over="ignore"):
        return (1.0 / (1.0 + np.exp(-x.astype(np.float64)))).astype(np.float32)


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-300, 1 - 1e-16)
    return np.log(p) - np.log1p(-p)


def _exp(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # an overflow to inf is found and named by the caller
        return np.exp(x.astype(np.float64)).astype(np.float32)


def _encode(activated: np.ndarray, forward, inverse) -> np.ndarray:
    """float32 raw values r with forward(r) == activated where such an r exists.

    The nearest float32 to inverse(a) maps back to a unless a lies on a rounding edge; then one
    of its two float32 neighbours does. Values no float32 raw reaches keep the nearest one.
    """
    a = activated.astype(np.float32)
    r0 = inverse(a.astype(np.float64)).astype(np.float32)
    best = r0.copy()
    found = forward(r0) == a
    for direction in (np.inf, -np.inf):
        cand = np.nextafter(r0, np.float32(direction))
        hit = ~found & (forward(cand) == a)
        best[hit] = cand[hit]
        found |= hit
    return best


def fitted_background(scene_file: Path) -> tuple[float, float, float] | None:
    """The `background` the fit_config.json beside `scene_file` records (a fit of `make
    scenes`), or None where there is no such file or it records no colour. A file that is not
    JSON, or a colour that is not three numbers in [0, 1], is refused naming the file: the
    scene would otherwise be rendered silently on another colour than it was fitted on."""
    path = Path(scene_file).parent / "fit_config.json"
    try:
        text = path.read_text()
    except OSError:
        return None
    try:
        record = json.loads(text)
    except ValueError as exc:
        raise SceneFileError(f"{path}: not JSON ({exc}); fix or remove it") from None
    colour = record.get("background") if isinstance(record, dict) else None
    if colour is None:
        return None
    numeric = [v for v in colour if type(v) in (int, float)] if isinstance(colour, list) else []
    if not (len(numeric) == 3 == len(colour) and all(0.0 <= v <= 1.0 for v in numeric)):
        raise SceneFileError(  # NaN fails the range too
            f"{path}: background {colour!r} is not three numbers r, g, b in [0, 1]"
        )
    return (float(colour[0]), float(colour[1]), float(colour[2]))
