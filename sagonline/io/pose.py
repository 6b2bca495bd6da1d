"""Camera-to-world poses and intrinsics from a file, turned into validated `Camera`s; every
problem raises CameraFileError naming the file and the frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sagonline.cameras import Camera, make_camera
from sagonline.errors import CameraFileError


def invert_pose(c2w: np.ndarray, path: Path, frame: str) -> np.ndarray:
    """World-to-camera from a camera-to-world 4x4; a singular one is refused naming the frame."""
    if not np.isfinite(c2w).all():
        raise CameraFileError(f"{path}: frame {frame!r}: its pose holds NaN/Inf")
    try:
        w2c = np.linalg.inv(c2w)
    except np.linalg.LinAlgError:
        raise CameraFileError(f"{path}: frame {frame!r} has a singular pose matrix") from None
    if not np.isfinite(w2c).all():
        raise CameraFileError(f"{path}: frame {frame!r} has a singular pose matrix")
    return w2c


def checked_camera(K, w2c, width, height, name: str, path: Path) -> Camera:
    """make_camera, with a failed validation naming the file (the message names the frame)."""
    try:
        return make_camera(K, w2c, width, height, name)
    except (ValueError, TypeError) as exc:
        raise CameraFileError(f"{path}: {exc}") from None
