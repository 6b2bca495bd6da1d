"""The 32-byte-per-splat `.splat` format: xyz f32, scales f32 (linear), RGBA u8, wxyz u8."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from sagonline.core.errors import SceneFileError
from sagonline.scene.gaussians import SH_C0, Gaussians
from sagonline.scene.io.scene_checks import check_finite, normalize_quats, require_scene_file


def read_splat(path: str | Path, *, drop_nonfinite: bool = False) -> Gaussians:
    """Read the 32-byte-per-splat format: xyz f32, scales f32 (linear), RGBA u8, wxyz u8."""
    path = Path(path)
    require_scene_file(path)
    buf = path.read_bytes()
    if len(buf) == 0 or len(buf) % 32:
        raise SceneFileError(
            f"{path}: {len(buf)} bytes is not a whole number of 32-byte splats "
            "(truncated or not a .splat file)"
        )
    dtype = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    data = np.frombuffer(buf, dtype=dtype)
    raw = {"means": data["pos"].copy(), "scales": data["scale"].copy()}
    raw = check_finite(path, raw, {"means": ["x", "y", "z"], "scales": ["scale"]}, drop_nonfinite)
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
        quats=torch.from_numpy(normalize_quats(path, quats, "rot bytes")),
        scales=torch.from_numpy(raw["scales"]),
        opacities=torch.from_numpy(rgba[:, 3].copy()),
        sh=torch.from_numpy(dc[:, None, :].copy()),
    )
