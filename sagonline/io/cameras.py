"""Camera files in the layouts datasets ship: 3DGS cameras.json, NeRF transforms.json, LLFF
poses_bounds.npy, COLMAP sparse models (and their points), .npz; all converted to OpenCV
`Camera`s at load time and validated (CameraFileError names the file)."""

from __future__ import annotations

import json
import struct
import warnings
from pathlib import Path

import numpy as np

from sagonline.cameras import Camera, intrinsics, make_camera
from sagonline.io.images import list_images


class CameraFileError(ValueError):
    """Camera file missing or malformed; the message names the file."""


def load_cameras(path: str | Path, **kwargs) -> list[Camera]:
    """Load cameras from any supported file or folder.

    `cameras.json` (3DGS output), `transforms*.json` (NeRF/Blender), `poses_bounds.npy` (LLFF),
    a COLMAP sparse folder (`cameras.bin`/`images.bin` or `.txt`), or a `.npz` with `viewmats`,
    `Ks`, `width`, `height`. A JSON file is read as NeRF or 3DGS by its content, whatever its
    name. A dataset folder is searched for those in that order. Every camera is validated
    (finite values, positive focal lengths and size, a rotation in the pose): any problem
    raises CameraFileError naming the file.
    """
    path = Path(path)
    try:
        return _load_cameras(path, **kwargs)
    except CameraFileError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, np.linalg.LinAlgError) as exc:
        raise CameraFileError(f"{path}: {exc}") from exc


CAMERA_FILES = (
    "cameras.json",
    "transforms.json",
    "transforms_train.json",
    "poses_bounds.npy",
    "sparse/0",
    "sparse",
)


def camera_source(path: str | Path) -> Path:
    """The file (or COLMAP model folder) `load_cameras(path)` reads: `path` itself, or for a
    dataset folder the first of CAMERA_FILES found in it."""
    path = Path(path)
    if not path.is_dir() or _is_colmap_dir(path):
        return path
    for candidate in CAMERA_FILES:
        found = path / candidate
        if found.exists() and (not found.is_dir() or _is_colmap_dir(found)):
            return found
    raise CameraFileError(
        f"{path}: no cameras found (looked for cameras.json, transforms.json, "
        "poses_bounds.npy, sparse/0 with cameras+images)"
    )


def camera_input_files(path: str | Path) -> list[Path]:
    """Every file `load_cameras(path)` reads (a COLMAP model: the files of its folder)."""
    source = camera_source(path)
    return sorted(p for p in source.iterdir() if p.is_file()) if source.is_dir() else [source]


def _load_cameras(path: Path, **kwargs) -> list[Camera]:
    if path.is_dir():
        source = camera_source(path)
        return load_colmap(source) if source.is_dir() else _load_cameras(source, **kwargs)
    if not path.exists():
        raise CameraFileError(f"{path}: camera file not found")
    name = path.name
    if name == "poses_bounds.npy":
        return load_llff(path.parent, **kwargs)
    if name.endswith(".json"):
        try:
            content = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise CameraFileError(f"{path}: not a readable JSON file ({exc})") from exc
        if isinstance(content, dict) and "frames" in content:
            return load_nerf_transforms(path, **kwargs)
        if isinstance(content, list):
            return load_3dgs_cameras_json(path)
        raise CameraFileError(
            f"{path}: neither NeRF transforms (an object with 'frames') nor a 3DGS "
            "cameras.json (a list of cameras)"
        )
    if name.endswith(".npz"):
        return load_npz_cameras(path)
    raise CameraFileError(f"{path}: unknown camera file type")


def _is_colmap_dir(path: Path) -> bool:
    return any((path / f"images.{ext}").exists() for ext in ("bin", "txt")) and any(
        (path / f"cameras.{ext}").exists() for ext in ("bin", "txt")
    )


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
        from PIL import Image

        with Image.open(images[0]) as im:
            width, height = im.size
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
        cams.append(_camera(K, w2c, width, height, Path(name).stem, pb_path))
    return cams


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


def _camera(K, w2c, width, height, name: str, path: Path) -> Camera:
    """make_camera, with a failed validation naming the file (the message names the frame)."""
    try:
        return make_camera(K, w2c, width, height, name)
    except (ValueError, TypeError) as exc:
        raise CameraFileError(f"{path}: {exc}") from None


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
    if not np.isfinite(arr).all():
        row = int(np.flatnonzero(~np.isfinite(arr).all(1))[0])
        raise CameraFileError(f"{path}: row {row} holds NaN/Inf")
    return arr


def load_llff_bounds(scene_dir: str | Path) -> np.ndarray:
    """(N, 2) near/far depth bounds from `poses_bounds.npy`."""
    return read_poses_bounds(Path(scene_dir) / "poses_bounds.npy")[:, 15:17]


def load_nerf_transforms(
    path: str | Path, width: int | None = None, height: int | None = None
) -> list[Camera]:
    """NeRF/Blender `transforms.json`: camera-to-world in OpenGL axes (x right, y up, z back).

    Focal length from `fl_x`/`fl_y` or `camera_angle_x`; size from `w`/`h` (top level or per
    frame) unless given.
    """
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CameraFileError(f"{path}: not a readable JSON file ({exc})") from exc
    if "frames" not in meta or not meta["frames"]:
        raise CameraFileError(f"{path}: no 'frames' list")
    cams = []
    for i, frame in enumerate(meta["frames"]):
        info = {**meta, **frame}
        w = width or info.get("w")
        h = height or info.get("h")
        if w is None or h is None:
            raise CameraFileError(
                f"{path}: frame {i} has no image size ('w'/'h'); pass width/height"
            )
        if "fl_x" in info:
            fx = info["fl_x"]
            fy = info.get("fl_y", fx)
        elif "camera_angle_x" in info:
            fx = 0.5 * w / np.tan(0.5 * field_of_view(info, "camera_angle_x", path, i))
            fy = fx
            if "camera_angle_y" in info:
                fy = 0.5 * h / np.tan(0.5 * field_of_view(info, "camera_angle_y", path, i))
        else:
            raise CameraFileError(f"{path}: frame {i} has no focal length (fl_x or camera_angle_x)")
        cx, cy = info.get("cx", w / 2.0), info.get("cy", h / 2.0)
        if "transform_matrix" not in frame:
            raise CameraFileError(f"{path}: frame {i} has no transform_matrix")
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64).reshape(4, 4)
        c2w[:3, 1:3] *= -1.0  # OpenGL -> OpenCV axes
        name = Path(str(frame.get("file_path", f"frame_{i:05d}"))).stem
        w2c = invert_pose(c2w, path, name)
        cams.append(_camera(intrinsics(fx, fy, cx, cy), w2c, w, h, name, path))
    return cams


# A pinhole sees less than 180 degrees; near it the focal length vanishes (pi gives 6e-14 px).
MAX_FIELD_OF_VIEW = np.deg2rad(179.0)


def field_of_view(info: dict, key: str, path: Path, frame: int) -> float:
    """A field of view in radians, checked to lie in (0, MAX_FIELD_OF_VIEW]."""
    angle = float(info[key])
    if not 0 < angle <= MAX_FIELD_OF_VIEW:
        raise CameraFileError(
            f"{path}: frame {frame}: {key}={angle:g} rad is not a pinhole field of view in "
            f"(0, {MAX_FIELD_OF_VIEW:.4f}] (179 degrees; radians, not degrees?)"
        )
    return angle


def load_3dgs_cameras_json(path: str | Path) -> list[Camera]:
    """The `cameras.json` written by 3DGS/2DGS training: camera-to-world `rotation` and
    `position` in COLMAP (OpenCV) axes, `fx`, `fy`, `width`, `height`, `img_name`."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CameraFileError(f"{path}: not a readable JSON file ({exc})") from exc
    if not isinstance(entries, list) or not entries:
        raise CameraFileError(f"{path}: expected a non-empty list of cameras")
    cams = []
    for i, e in enumerate(entries):
        missing = [k for k in ("rotation", "position", "fx", "fy", "width", "height") if k not in e]
        if missing:
            raise CameraFileError(f"{path}: camera {i} lacks {missing}")
        c2w = np.eye(4)
        c2w[:3, :3] = np.asarray(e["rotation"], dtype=np.float64)
        c2w[:3, 3] = np.asarray(e["position"], dtype=np.float64)
        w, h = int(e["width"]), int(e["height"])
        K = intrinsics(e["fx"], e["fy"], w / 2.0, h / 2.0)
        name = str(e.get("img_name", i))
        cams.append(_camera(K, invert_pose(c2w, path, name), w, h, name, path))
    return sorted(cams, key=lambda c: c.name)


def write_3dgs_cameras_json(path: str | Path, cameras: list[Camera]) -> Path:
    """Write cameras in the 3DGS `cameras.json` layout (principal point assumed central)."""
    entries = []
    for i, cam in enumerate(cameras):
        c2w = cam.cam_to_world.double().numpy()
        entries.append(
            {
                "id": i,
                "img_name": cam.name,
                "width": cam.width,
                "height": cam.height,
                "position": c2w[:3, 3].tolist(),
                "rotation": c2w[:3, :3].tolist(),
                "fx": float(cam.K[0, 0]),
                "fy": float(cam.K[1, 1]),
            }
        )
    from sagonline.utils import atomic_write_text

    return atomic_write_text(path, json.dumps(entries, indent=1))


def load_npz_cameras(path: str | Path) -> list[Camera]:
    """A `.npz` with `viewmats` (N, 4, 4) world-to-camera, `Ks` (N, 3, 3), `width`, `height`."""
    path = Path(path)
    z = np.load(path)
    for key in ("viewmats", "Ks", "width", "height"):
        if key not in z:
            raise CameraFileError(f"{path}: missing array {key!r}")
    return [
        make_camera(K, vm, int(z["width"]), int(z["height"]), f"{i:05d}")
        for i, (K, vm) in enumerate(zip(z["Ks"], z["viewmats"], strict=True))
    ]


def load_colmap(sparse_dir: str | Path) -> list[Camera]:
    """COLMAP sparse model (binary or text) through pycolmap; sorted by image name.

    Distortion parameters are ignored with a warning: Gaussian scenes are trained on undistorted
    images, so use the model COLMAP's undistorter wrote.
    """
    import pycolmap

    sparse_dir = Path(sparse_dir)
    if not _is_colmap_dir(sparse_dir):
        raise CameraFileError(
            f"{sparse_dir}: not a COLMAP model (needs cameras and images, .bin or .txt)"
        )
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:
        raise CameraFileError(f"{sparse_dir}: pycolmap could not read the model ({exc})") from exc
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
