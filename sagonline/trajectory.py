"""Camera trajectories a video segmenter can watch: pseudo-temporal order and smooth paths."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from sagonline.cameras import Camera, make_camera


def pseudo_temporal_order(cameras: list[Camera]) -> list[Camera]:
    """The dataset's views sorted lexicographically by name (the NVOS / SPIn-NeRF protocol)."""
    return sorted(cameras, key=lambda c: c.name)


def smooth_path(keyframes: list[Camera], num_frames: int, *, loop: bool = False) -> list[Camera]:
    """`num_frames` cameras along the keyframes: slerped rotations, interpolated centres and
    intrinsics, evenly spaced in keyframe parameter. All keyframes must share one image size
    (rescale with `Camera.scaled` first). With `loop`, the path returns to the first keyframe.
    """
    if len(keyframes) < 1 or num_frames < 1:
        raise ValueError("smooth_path needs at least one keyframe and one frame")
    sizes = {(c.width, c.height) for c in keyframes}
    if len(sizes) > 1:
        raise ValueError(
            f"keyframes have different image sizes {sorted(sizes)}; rescale them first"
        )
    keys = list(keyframes) + ([keyframes[0]] if loop else [])
    if len(keys) == 1:
        return [keys[0]] * num_frames
    w2c = np.stack([c.world_to_cam.double().numpy() for c in keys])
    c2w_rot = np.transpose(w2c[:, :3, :3], (0, 2, 1))
    centers = np.stack([c.center.double().numpy() for c in keys])
    Ks = np.stack([c.K.double().numpy() for c in keys])
    knots = np.arange(len(keys), dtype=np.float64)
    slerp = Slerp(knots, Rotation.from_matrix(c2w_rot))
    end = len(keys) - 1
    ts = np.linspace(0.0, end, num_frames, endpoint=not loop)
    rots = slerp(ts).as_matrix()
    width, height = keys[0].width, keys[0].height
    path = []
    for i, t in enumerate(ts):
        j = min(int(np.floor(t)), end - 1)
        a = t - j
        center = (1 - a) * centers[j] + a * centers[j + 1]
        K = (1 - a) * Ks[j] + a * Ks[j + 1]
        m = np.eye(4)
        m[:3, :3] = rots[i].T
        m[:3, 3] = -rots[i].T @ center
        path.append(make_camera(K, m, width, height, f"path_{i:05d}"))
    return path


def orbit(
    center,
    radius: float,
    height: float,
    num_frames: int,
    K: np.ndarray,
    width: int,
    height_px: int,
    *,
    up=(0.0, 0.0, 1.0),
    start_deg: float = 0.0,
    span_deg: float = 360.0,
    prefix: str = "orbit",
) -> list[Camera]:
    """Cameras on a circle around `center` at `height` above it, all looking at `center`."""
    from sagonline.cameras import look_at

    center = np.asarray(center, dtype=np.float64)
    full = abs(span_deg - 360.0) < 1e-9
    angles = np.deg2rad(start_deg + np.linspace(0.0, span_deg, num_frames, endpoint=not full))
    cams = []
    for i, a in enumerate(angles):
        eye = center + np.array([radius * np.cos(a), radius * np.sin(a), height])
        cams.append(make_camera(K, look_at(eye, center, up), width, height_px, f"{prefix}_{i:05d}"))
    return cams


def cameras_to_tensors(cameras: list[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
    """(C, 4, 4) world-to-camera and (C, 3, 3) intrinsics stacked."""
    return (torch.stack([c.world_to_cam for c in cameras]), torch.stack([c.K for c in cameras]))
