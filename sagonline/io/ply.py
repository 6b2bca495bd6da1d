"""Read and write trained Gaussian scenes: 3DGS / 2DGS `point_cloud.ply` and 32-byte `.splat`.

Raw file values (opacity logit, log scales, unnormalised wxyz quaternions) exist only here; the
rest of the library sees activated `Gaussians`. Writing chooses, for every activated value, the
float32 raw value whose activation rounds back to it, so `read(write(g)) == g` bit for bit for
any scene that was read from a file.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from sagonline.gaussians import SH_C0, Gaussians, sh_degree_from_coeffs
from sagonline.utils import atomic_write


class SceneFileError(ValueError):
    """A scene file is missing, truncated or malformed; the message names the file and field."""


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
        return read_splat(path, drop_nonfinite=drop_nonfinite)
    return read_ply(path, drop_nonfinite=drop_nonfinite)


def read_ply(path: str | Path, *, drop_nonfinite: bool = False) -> Gaussians:
    """Read the 3DGS (scale_0..2) or 2DGS (scale_0..1) `point_cloud.ply` layout."""
    path = Path(path)
    if not path.is_file():
        raise SceneFileError(f"{path}: scene file not found")
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several types for truncated/garbled input
        raise SceneFileError(
            f"{path}: not a readable PLY file ({type(exc).__name__}: {exc})"
        ) from exc
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise SceneFileError(
            f"{path}: no 'vertex' element (found elements {names}); "
            "a Gaussian PLY stores one vertex per Gaussian"
        )
    vertex = ply["vertex"]
    props = [p.name for p in vertex.properties]
    missing = [p for p in _REQUIRED if p not in props]
    if missing:
        raise SceneFileError(
            f"{path}: missing required property {missing[0]!r} (all missing: {missing})"
        )
    data = vertex.data
    if len(data) == 0:
        raise SceneFileError(f"{path}: the vertex element is empty")

    def column(name: str) -> np.ndarray:
        return np.asarray(data[name], dtype=np.float32)

    def stack(names: list[str]) -> np.ndarray:
        return np.stack([column(n) for n in names], axis=1)

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
    scale_names = ["scale_0", "scale_1"] + (["scale_2"] if "scale_2" in props else [])
    has_normals = all(n in props for n in ("nx", "ny", "nz"))

    raw = {
        "means": stack(["x", "y", "z"]),
        "dc": stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
        "rest": stack(rest_names) if rest_names else np.zeros((len(data), 0), np.float32),
        "opacity": column("opacity")[:, None],
        "scales": stack(scale_names),
        "quats": stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
    }
    if has_normals:
        raw["normals"] = stack(["nx", "ny", "nz"])
    prop_names = {
        "means": ["x", "y", "z"],
        "dc": ["f_dc_0", "f_dc_1", "f_dc_2"],
        "rest": rest_names,
        "opacity": ["opacity"],
        "scales": scale_names,
        "quats": ["rot_0", "rot_1", "rot_2", "rot_3"],
        "normals": ["nx", "ny", "nz"],
    }
    raw = _check_finite(path, raw, prop_names, drop_nonfinite)
    n = raw["means"].shape[0]
    k = raw["rest"].shape[1] // 3
    sh = np.concatenate([raw["dc"][:, None, :], raw["rest"].reshape(n, 3, k).transpose(0, 2, 1)], 1)
    return Gaussians(
        means=torch.from_numpy(raw["means"]),
        quats=torch.from_numpy(_normalize_quats(path, raw["quats"], "rot_0..rot_3")),
        scales=torch.from_numpy(_exp(raw["scales"])),
        opacities=torch.from_numpy(_sigmoid(raw["opacity"][:, 0])),
        sh=torch.from_numpy(np.ascontiguousarray(sh)),
        normals=torch.from_numpy(raw["normals"]) if has_normals else None,
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


def read_splat(path: str | Path, *, drop_nonfinite: bool = False) -> Gaussians:
    """Read the 32-byte-per-splat format: xyz f32, scales f32 (linear), RGBA u8, wxyz u8."""
    path = Path(path)
    if not path.is_file():
        raise SceneFileError(f"{path}: scene file not found")
    buf = path.read_bytes()
    if len(buf) == 0 or len(buf) % 32:
        raise SceneFileError(
            f"{path}: {len(buf)} bytes is not a whole number of 32-byte splats "
            "(truncated or not a .splat file)"
        )
    dtype = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    data = np.frombuffer(buf, dtype=dtype)
    raw = {"means": data["pos"].copy(), "scales": data["scale"].copy()}
    raw = _check_finite(path, raw, {"means": ["x", "y", "z"], "scales": ["scale"]}, drop_nonfinite)
    if drop_nonfinite:
        data = data[np.isfinite(data["pos"]).all(1) & np.isfinite(data["scale"]).all(1)]
    if (raw["scales"] <= 0).any():
        bad = int((raw["scales"] <= 0).any(1).sum())
        raise SceneFileError(f"{path}: {bad} splats have non-positive scale")
    rgba = data["rgba"].astype(np.float32) / 255.0
    quats = (data["rot"].astype(np.float32) - 128.0) / 128.0
    dc = (rgba[:, :3] - 0.5) / SH_C0
    return Gaussians(
        means=torch.from_numpy(raw["means"]),
        quats=torch.from_numpy(_normalize_quats(path, quats, "rot bytes")),
        scales=torch.from_numpy(raw["scales"]),
        opacities=torch.from_numpy(rgba[:, 3].copy()),
        sh=torch.from_numpy(dc[:, None, :].copy()),
    )


# --- raw <-> activated ------------------------------------------------------------------------


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-x.astype(np.float64)))).astype(np.float32)


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-300, 1 - 1e-16)
    return np.log(p) - np.log1p(-p)


def _exp(x: np.ndarray) -> np.ndarray:
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


def _normalize_quats(path: Path, quats: np.ndarray, what: str) -> np.ndarray:
    norm = np.linalg.norm(quats.astype(np.float64), axis=1)
    zero = norm < 1e-12
    if zero.any():
        rows = np.flatnonzero(zero)
        raise SceneFileError(
            f"{path}: {len(rows)} zero-norm quaternions in {what} (first at row {rows[0]})"
        )
    # Rows already unit to float32 precision stay as they are, so a write/read cycle is exact.
    unit = np.abs(norm - 1.0) < 1e-6
    out = (quats.astype(np.float64) / norm[:, None]).astype(np.float32)
    out[unit] = quats[unit]
    return out


def _check_finite(
    path: Path, raw: dict[str, np.ndarray], names: dict[str, list[str]], drop: bool
) -> dict[str, np.ndarray]:
    n = next(iter(raw.values())).shape[0]
    bad_rows = np.zeros(n, dtype=bool)
    first_bad: tuple[str, int, int] | None = None
    for key, values in raw.items():
        bad = ~np.isfinite(values)
        if bad.any():
            rows, cols = np.nonzero(bad)
            bad_rows[rows] = True
            if first_bad is None:
                first_bad = (
                    names[key][min(cols[0], len(names[key]) - 1)],
                    int(rows[0]),
                    int(bad.any(1).sum()),
                )
    if first_bad is None:
        return raw
    prop, row, count = first_bad
    if not drop:
        raise SceneFileError(
            f"{path}: property {prop!r} has NaN/Inf values ({count} rows, first at row {row}); "
            f"{int(bad_rows.sum())} rows are non-finite in all. Pass drop_nonfinite=True "
            "(CLI: --drop-nonfinite) to drop them."
        )
    warnings.warn(
        f"{path}: dropped {int(bad_rows.sum())} of {n} Gaussians with NaN/Inf values", stacklevel=3
    )
    keep = ~bad_rows
    if not keep.any():
        raise SceneFileError(f"{path}: every Gaussian has NaN/Inf values")
    return {k: v[keep] for k, v in raw.items()}
