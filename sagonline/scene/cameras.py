"""Pinhole cameras in the OpenCV convention (their loaders: `sagonline.scene.io.cameras`).

Inside the library: x right, y down, z forward; `world_to_cam` is a 4x4 rigid transform; `K` is
3x3 in pixels with pixel centres at +0.5 (pixel (0, 0) covers [0, 1) x [0, 1)). Every other
convention (LLFF, NeRF/Blender OpenGL axes, COLMAP) is converted at load time, in the loaders.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from numbers import Integral

import numpy as np
import torch

# The most pixels one view may have: a render allocates several float32 buffers of this many
# pixels, so a mistyped size (100000 x 100000) is refused by name instead of exhausting memory.
MAX_PIXELS = int(os.environ.get("SAGONLINE_MAX_PIXELS", 8192 * 8192))


@dataclass(frozen=True)
class Camera:
    """One view: intrinsics `K` (3, 3), `world_to_cam` (4, 4), image size, and a name."""

    K: torch.Tensor
    world_to_cam: torch.Tensor
    width: int
    height: int
    name: str = ""

    def __post_init__(self) -> None:
        who = f"camera {self.name!r}"
        if tuple(self.K.shape) != (3, 3) or tuple(self.world_to_cam.shape) != (4, 4):
            raise ValueError(
                f"{who}: K must be 3x3 and world_to_cam 4x4, got {tuple(self.K.shape)} and "
                f"{tuple(self.world_to_cam.shape)}"
            )
        if not (isinstance(self.width, Integral) and isinstance(self.height, Integral)):
            raise ValueError(f"{who}: size {self.width!r}x{self.height!r} is not two integers")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"{who}: size {self.width}x{self.height} is not positive")
        if self.width * self.height > MAX_PIXELS:
            raise ValueError(
                f"{who}: {self.width}x{self.height} = {self.width * self.height:,} pixels exceeds "
                f"the ceiling of {MAX_PIXELS:,} (sagonline.scene.cameras.MAX_PIXELS; the "
                "environment variable SAGONLINE_MAX_PIXELS raises it)"
            )
        K, pose = self.K.detach().double().cpu(), self.world_to_cam.detach().double().cpu()
        if not (torch.isfinite(K).all() and torch.isfinite(pose).all()):
            raise ValueError(f"{who}: intrinsics or pose hold NaN/Inf")
        fx, fy = float(K[0, 0]), float(K[1, 1])
        if fx <= 0 or fy <= 0:
            raise ValueError(f"{who}: focal lengths fx={fx:g}, fy={fy:g} must be positive")
        R = pose[:3, :3]
        off = (R @ R.T - torch.eye(3, dtype=R.dtype)).abs().max()
        if off > 1e-3 or torch.linalg.det(R) <= 0:
            raise ValueError(
                f"{who}: the pose's rotation is not a rotation (|R R^T - I| = {float(off):.3g}, "
                f"det {float(torch.linalg.det(R)):.3g}): singular, scaled or mirrored matrix"
            )

    @property
    def rotation(
        self,
    ) -> torch.Tensor:  # [3, 3] world-to-camera rotation
        """(3, 3) world-to-camera rotation."""
        return self.world_to_cam[:3, :3]

    @property
    def translation(
        self,
    ) -> torch.Tensor:  # [3]
        return self.world_to_cam[:3, 3]

    @property
    def center(
        self,
    ) -> torch.Tensor:  # [3] camera centre, world coordinates
        """(3,) camera centre in world coordinates."""
        return -self.rotation.T @ self.translation

    @property
    def cam_to_world(
        self,
    ) -> torch.Tensor:  # [4, 4]
        return torch.linalg.inv(self.world_to_cam)

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera rendering at another resolution (intrinsics rescaled per axis)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[0] *= sx
        K[1] *= sy
        return replace(self, K=K, width=int(width), height=int(height))

    def to(self, device: torch.device | str) -> Camera:
        """The camera on `device`: itself where it is there already (a render calls this per
        view, and a new camera's checks read its values on the host: a wait on the GPU)."""
        where = torch.device(device)
        if where.type == "cuda" and where.index is None:
            where = torch.device("cuda", torch.cuda.current_device())
        if self.K.device == where and self.world_to_cam.device == where:
            return self
        return replace(self, K=self.K.to(device), world_to_cam=self.world_to_cam.to(device))

    def project(
        self,
        points: torch.Tensor,  # [N, 3] world points
    ) -> tuple[torch.Tensor, torch.Tensor]:  # [N, 2] pixels, [N] camera depth
        """(N, 3) world points -> (N, 2) pixel coordinates and (N,) camera-space depth."""
        cam = points @ self.rotation.T + self.translation
        uvw = cam @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3].clamp_min(1e-12), cam[:, 2]

    def in_frame(
        self,
        points: torch.Tensor,  # [N, 3] world points
    ) -> tuple[torch.Tensor, torch.Tensor]:  # [N] bool inside, [N] depth
        """(N, 3) world points -> (N,) bool: in front of the camera and inside the image, and
        (N,) camera-space depth."""
        uv, z = self.project(points)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width)
        return inside & (uv[:, 1] >= 0) & (uv[:, 1] < self.height), z


def make_camera(K, world_to_cam, width: int, height: int, name: str = "") -> Camera:
    """A Camera from array-likes; the size must be two whole numbers (not flags or strings)."""
    return Camera(
        torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=torch.float32),
        torch.as_tensor(np.asarray(world_to_cam, dtype=np.float64), dtype=torch.float32),
        whole_pixels(width, f"camera {name!r}: width"),
        whole_pixels(height, f"camera {name!r}: height"),
        name,
    )


def whole_pixels(value, what: str) -> int:
    """An image size read from a file as an int; a flag, a string or a fraction is refused."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (Integral, float, np.floating)):
        raise ValueError(f"{what} {value!r} is not a whole number of pixels")
    if isinstance(value, (float, np.floating)) and not float(value).is_integer():
        raise ValueError(f"{what} {value!r} is not a whole number of pixels")
    return int(value)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera 4x4 for an OpenCV camera at `eye` looking at `target` (`up` is world up)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# --- loaders --------------------------------------------------------------------------------
