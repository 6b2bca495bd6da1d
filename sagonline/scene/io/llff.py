"""LLFF captures: `poses_bounds.npy`, read without trusting its header (no pickle, no allocation
the file cannot back)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from sagonline.core.errors import CameraFileError
from sagonline.scene.cameras import Camera, intrinsics
from sagonline.scene.io.images import list_images
from sagonline.scene.io.pose import check_count, checked_camera, invert_pose


def load_llff(
    scene_dir: str | Path, image_dir: str | None = None, names: list[str] | None = None
) -> list[Camera]:
    """LLFF `poses_bounds.npy`: rows of a 3x5 [R | t | (H, W, f)] camera-to-world (axes down,
    right, backwards) and two depth bounds, at the full resolution.

    Row i belongs to the i-th image name in sorted order (`names` overrides the listing). With
    `image_dir` (e.g. "images_4"), intrinsics are rescaled to the size of the images found there.
    """
    scene_dir = Path(scene_dir)
    pb_path = scene_dir / "poses_bounds.npy"
    if not pb_path.is_file():
        raise CameraFileError(f"{pb_path}: LLFF poses_bounds.npy not found")
    arr = read_poses_bounds(pb_path)
    poses = arr[:, :15].reshape(-1, 3, 5)
    full_h, full_w, focal = poses[0, :, 4]
    width, height = int(round(full_w)), int(round(full_h))
    if image_dir is not None:
        images = list_images(scene_dir / image_dir)
        if not images:
            raise CameraFileError(f"{scene_dir / image_dir}: no images to size the cameras by")
        from sagonline.scene.io.images import image_size

        width, height = image_size(images[0])
        if names is None:
            names = [p.stem for p in images]
    if names is None:
        names = [f"{i:05d}" for i in range(len(arr))]
    if len(names) != len(arr):
        raise CameraFileError(
            f"{pb_path}: {len(arr)} poses but {len(names)} image names; "
            "pass the full sorted name list (names=...)"
        )
    sx, sy = width / full_w, height / full_h
    cams = []
    for pose, name in zip(poses, names, strict=True):
        h, w, f = pose[:, 4]
        c2w = np.eye(4)
        # LLFF columns are (down, right, back); OpenCV wants (right, down, forward).
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = pose[:, 1], pose[:, 0], -pose[:, 2]
        c2w[:3, 3] = pose[:, 3]
        K = intrinsics(f * sx, f * sy, w * sx / 2.0, h * sy / 2.0)
        w2c = invert_pose(c2w, pb_path, Path(name).stem)
        cams.append(checked_camera(K, w2c, width, height, Path(name).stem, pb_path))
    return cams


def photo_folder(scene_dir: str | Path) -> str | None:
    """The folder beside `poses_bounds.npy` with one image per pose, to size and name its
    cameras by: LLFF's photographs, `images/` or a downsampled `images_<N>/`, else a `masks/` or
    `masks_<N>/` (the NeRD captures': a mask for every pose, photographs of some). Of several,
    the most downsampled (the lightest renders; a command's --width/--height give any other
    size). None where no folder has one image per pose."""
    scene_dir = Path(scene_dir)
    poses = len(read_poses_bounds(scene_dir / "poses_bounds.npy"))
    ranked = {}
    for folder in scene_dir.iterdir() if scene_dir.is_dir() else ():
        found = re.fullmatch(r"(images|masks)(?:_(\d+))?", folder.name)
        if found and folder.is_dir() and len(list_images(folder)) == poses:
            ranked[folder.name] = (found.group(1) == "images", int(found.group(2) or 1))
    return max(ranked, key=lambda name: (ranked[name], name)) if ranked else None


def read_npy(path: Path, error: type[Exception]) -> np.ndarray:
    """A numeric `.npy` array, its header checked against the file's size before anything is
    allocated (a damaged header cannot ask for terabytes); never unpickles."""
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read_header = {
                (1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0,
            }.get(version)
            if read_header is None:
                raise ValueError(f".npy format version {version} is not supported")
            shape, _, dtype = read_header(f)
            data_bytes = path.stat().st_size - f.tell()
    except Exception as exc:  # the header is parsed (ast.literal_eval), never executed
        raise error(f"{path}: not a readable .npy array ({type(exc).__name__}: {exc})") from None
    if dtype.kind not in "biuf" or dtype.hasobject:
        raise error(f"{path}: holds {dtype} values, not numbers")
    if int(np.prod(shape, dtype=np.float64)) * dtype.itemsize != data_bytes:
        raise error(
            f"{path}: its header says {shape} {dtype} but the file holds {data_bytes} bytes "
            "of data (truncated or damaged)"
        )
    return np.load(path, allow_pickle=False).astype(np.float64, copy=False)


def read_poses_bounds(path: str | Path) -> np.ndarray:
    """The (N, 17) float64 rows of an LLFF `poses_bounds.npy`, checked (CameraFileError)."""
    path = Path(path)
    arr = read_npy(path, CameraFileError)
    if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0:
        raise CameraFileError(f"{path}: expected an (N, 17) array, got {arr.shape}")
    check_count(len(arr), path)
    if not np.isfinite(arr).all():
        row = int(np.flatnonzero(~np.isfinite(arr).all(1))[0])
        raise CameraFileError(f"{path}: row {row} holds NaN/Inf")
    return arr


def load_llff_bounds(scene_dir: str | Path) -> np.ndarray:
    """(N, 2) near/far depth bounds from `poses_bounds.npy`."""
    return read_poses_bounds(Path(scene_dir) / "poses_bounds.npy")[:, 15:17]
