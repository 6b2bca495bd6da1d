"""Camera-to-world poses and intrinsics from a file, turned into validated `Camera`s; every
problem raises CameraFileError naming the file and the frame."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sagonline.core.errors import CameraFileError
from sagonline.scene.cameras import Camera, make_camera


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


# The most cameras one file may hold: every camera is parsed and validated, so a mistyped or
# hostile file (a million frames) is refused by name instead of taking minutes and gigabytes.
MAX_CAMERAS = int(os.environ.get("SAGONLINE_MAX_CAMERAS", 20_000))


def check_count(count: int, path: Path) -> None:
    if count > MAX_CAMERAS:
        raise CameraFileError(
            f"{path}: {count:,} cameras exceed the ceiling of {MAX_CAMERAS:,} "
            "(sagonline.scene.io.pose.MAX_CAMERAS; the environment variable "
            "SAGONLINE_MAX_CAMERAS raises it)"
        )


def check_unique_names(cams: list[Camera], path: Path) -> None:
    """Cameras are addressed by name (`--click NAME:...`, masks matched to views): two of one
    name are refused, naming both frames."""
    first: dict[str, int] = {}
    for i, cam in enumerate(cams):
        if cam.name in first:
            raise CameraFileError(
                f"{path}: frames {first[cam.name]} and {i} are both named {cam.name!r}; camera "
                "names must be unique (they name the views)"
            )
        first[cam.name] = i
