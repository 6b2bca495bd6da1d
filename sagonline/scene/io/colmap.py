"""COLMAP sparse models: cameras through pycolmap, points parsed directly."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np

from sagonline.core.errors import CameraFileError
from sagonline.scene.cameras import Camera, make_camera
from sagonline.scene.io.pose import check_count


def is_colmap_dir(path: Path) -> bool:
    return any((path / f"images.{ext}").exists() for ext in ("bin", "txt")) and any(
        (path / f"cameras.{ext}").exists() for ext in ("bin", "txt")
    )


def load_colmap(sparse_dir: str | Path) -> list[Camera]:
    """COLMAP sparse model (binary or text) through pycolmap; sorted by image name.

    Distortion parameters are ignored with a warning: Gaussian scenes are trained on undistorted
    images, so use the model COLMAP's undistorter wrote.
    """
    import pycolmap

    sparse_dir = Path(sparse_dir)
    if not is_colmap_dir(sparse_dir):
        raise CameraFileError(
            f"{sparse_dir}: not a COLMAP model (needs cameras and images, .bin or .txt)"
        )
    check_quaternions(sparse_dir)
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:
        raise CameraFileError(f"{sparse_dir}: pycolmap could not read the model ({exc})") from exc
    check_count(len(rec.images), sparse_dir)
    cams = []
    distorted = set()
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        if cam.model.name not in ("PINHOLE", "SIMPLE_PINHOLE"):
            distorted.add(cam.model.name)
        w2c = np.eye(4)
        w2c[:3, :] = image.cam_from_world().matrix()
        cams.append(
            make_camera(cam.calibration_matrix(), w2c, cam.width, cam.height, Path(image.name).stem)
        )
    if distorted:
        warnings.warn(
            f"{sparse_dir}: camera models {sorted(distorted)} have distortion that the "
            "rasterizer ignores; use an undistorted model",
            stacklevel=2,
        )
    return sorted(cams, key=lambda c: c.name)


def check_quaternions(sparse_dir: Path) -> None:
    """Refuse an image whose rotation quaternion is zero or not finite: COLMAP's reader would
    normalise it into some rotation (identity) without a word."""
    for name, q in raw_quaternions(sparse_dir):
        norm = float(np.linalg.norm(q))
        if not np.isfinite(q).all() or norm < 1e-8:
            raise CameraFileError(
                f"{sparse_dir}: image {name!r} has the rotation quaternion {list(q)}, which is "
                "no rotation (zero or not finite)"
            )


def raw_quaternions(sparse_dir: Path):
    """(image name, (4,) qw qx qy qz) as written in images.txt or images.bin."""
    txt, binary = sparse_dir / "images.txt", sparse_dir / "images.bin"
    if txt.is_file() and not binary.is_file():
        lines = [ln for ln in txt.read_text().splitlines() if not ln.startswith("#")]
        while lines and not lines[-1].strip():
            lines.pop()
        for line in lines[::2]:  # each image: a pose line, then its 2D points (maybe empty)
            parts = line.split()
            if len(parts) >= 10:
                try:
                    yield parts[9], np.array([float(v) for v in parts[1:5]])
                except ValueError:
                    raise CameraFileError(f"{txt}: {line[:60]!r} is not an image line") from None
        return
    if not binary.is_file():
        return
    buf = binary.read_bytes()
    try:
        (count,) = struct.unpack_from("<Q", buf, 0)
        offset = 8
        for _ in range(count):
            q = np.array(struct.unpack_from("<4d", buf, offset + 4))
            end = buf.index(b"\0", offset + 64)
            name = buf[offset + 64 : end].decode(errors="replace")
            (points,) = struct.unpack_from("<Q", buf, end + 1)
            offset = end + 1 + 8 + 24 * points
            yield name, q
    except (struct.error, ValueError) as exc:
        raise CameraFileError(f"{binary}: truncated COLMAP images file ({exc})") from None


def read_colmap_points(sparse_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) xyz and (P, 3) uint8 colours from `points3D.bin` or `.txt`.

    Parsed directly rather than through pycolmap, which refuses a model whose `images` file is
    absent (LLFF releases ship `cameras.bin` and `points3D.bin` only).
    """
    sparse_dir = Path(sparse_dir)
    bin_path, txt_path = sparse_dir / "points3D.bin", sparse_dir / "points3D.txt"
    if bin_path.is_file():
        return _read_points3d_bin(bin_path)
    if txt_path.is_file():
        rows = [
            ln.split()
            for ln in txt_path.read_text().splitlines()
            if ln.strip() and not ln.startswith("#")
        ]
        xyz = np.array([[float(v) for v in r[1:4]] for r in rows]).reshape(-1, 3)
        rgb = np.array([[int(v) for v in r[4:7]] for r in rows], dtype=np.uint8).reshape(-1, 3)
        return xyz, rgb
    raise CameraFileError(f"{sparse_dir}: no points3D.bin or points3D.txt")


def _read_points3d_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    buf = path.read_bytes()
    try:
        (count,) = struct.unpack_from("<Q", buf, 0)
        xyz = np.empty((count, 3))
        rgb = np.empty((count, 3), dtype=np.uint8)
        offset = 8
        for i in range(count):
            _, x, y, z, r, g, b, _, track_len = struct.unpack_from("<Q3d3BdQ", buf, offset)
            xyz[i], rgb[i] = (x, y, z), (r, g, b)
            offset += 51 + 8 * track_len
    except struct.error as exc:
        raise CameraFileError(f"{path}: truncated COLMAP points file ({exc})") from exc
    return xyz, rgb
