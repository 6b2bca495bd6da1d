"""Camera files in the layouts datasets ship: 3DGS cameras.json, NeRF transforms.json, LLFF
poses_bounds.npy, COLMAP sparse models (and their points), .npz; all converted to OpenCV
`Camera`s at load time and validated (CameraFileError names the file)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sagonline.core.errors import CameraFileError
from sagonline.scene.cameras import Camera, intrinsics, make_camera
from sagonline.scene.io.colmap import is_colmap_dir, load_colmap, read_colmap_points
from sagonline.scene.io.images import list_images
from sagonline.scene.io.llff import (
    load_llff,
    load_llff_bounds,
    photo_folder,
    read_npy,
    read_poses_bounds,
)
from sagonline.scene.io.pose import check_count, check_unique_names, checked_camera, invert_pose

__all__ = [
    "CameraFileError",
    "camera_digests",
    "camera_input_files",
    "camera_source",
    "cameras_beside",
    "llff_image_folder",
    "load_cameras",
    "load_colmap",
    "load_llff",
    "load_llff_bounds",
    "load_nerf_transforms",
    "read_colmap_points",
    "read_npy",
    "read_poses_bounds",
    "write_3dgs_cameras_json",
]


def load_cameras(path: str | Path, **kwargs) -> list[Camera]:
    """Load cameras from any supported file or folder.

    `cameras.json` (3DGS output), `transforms*.json` (NeRF/Blender), `poses_bounds.npy` (LLFF;
    sized and named by the images beside it: `llff.photo_folder`),
    a COLMAP sparse folder (`cameras.bin`/`images.bin` or `.txt`), or a `.npz` with `viewmats`,
    `Ks`, `width`, `height`. A JSON file is read as NeRF or 3DGS by its content, whatever its
    name. A dataset folder is searched for those in that order. Every camera is validated
    (finite values, positive focal lengths and size, a rotation in the pose): any problem
    raises CameraFileError naming the file. Names must be unique.

    The cameras come back **sorted by name**: the one order every command numbers views in
    (`sagonline cameras` prints it), whatever order the file lists them in.
    """
    path = Path(path)
    try:
        cams = _load_cameras(path, **kwargs)
    except CameraFileError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, np.linalg.LinAlgError) as exc:
        raise CameraFileError(f"{path}: {exc}") from exc
    check_unique_names(cams, path)
    return sorted(cams, key=lambda c: c.name)


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
    if not path.is_dir() or is_colmap_dir(path):
        return path
    for candidate in CAMERA_FILES:
        found = path / candidate
        if found.exists() and (not found.is_dir() or is_colmap_dir(found)):
            return found
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if any((folder / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
            raise CameraFileError(
                f"{folder}: a COLMAP model without images.bin or images.txt: its cameras.* holds "
                "the intrinsics only; the poses are in images.*"
            )
    raise CameraFileError(
        f"{path}: no cameras found (looked for cameras.json, transforms.json, "
        "poses_bounds.npy, sparse/0 with cameras+images)"
    )


def cameras_beside(scene: str | Path) -> Path | None:
    """The camera file a scene file was fitted or trained with, where one lies beside it: in
    the scene file's folder (a `make scenes` fit's cameras.json), else two folders up from a
    3DGS training output's point_cloud/iteration_<N>/point_cloud.ply (its cameras.json); the
    first of CAMERA_FILES there (`camera_source`), None where neither holds one."""
    folder = Path(scene).parent
    places = [folder, folder.parent.parent] if folder.parent.name == "point_cloud" else [folder]
    for place in (p for p in places if p.is_dir()):
        try:
            return camera_source(place)
        except CameraFileError:  # none there (or a COLMAP model without its poses)
            continue
    return None


def camera_input_files(path: str | Path) -> list[Path]:
    """Every file `load_cameras(path)` reads (a COLMAP model: the files of its folder; LLFF
    poses: with the images that size and name them, `llff_image_folder`)."""
    source = camera_source(path)
    if source.is_dir():
        return sorted(p for p in source.iterdir() if p.is_file())
    folder = llff_image_folder(source)
    return [source, *(list_images(folder) if folder else [])]


def camera_digests(path: str | Path) -> dict[str, str]:
    """Each file `load_cameras(path)` reads, as a segment folder's labels.json records it among
    its `inputs`: `cameras:<name>` -> its digest."""
    from sagonline.core.provenance import digest_file

    return {f"cameras:{p.name}": digest_file(p) for p in camera_input_files(path)}


def llff_image_folder(path: str | Path) -> Path | None:
    """The folder whose images size and name the cameras `load_cameras(path)` reads from LLFF
    poses (`llff.photo_folder`); None for any other camera file, or poses without one."""
    source = camera_source(path)
    if source.is_dir() or source.name != "poses_bounds.npy":
        return None
    folder = photo_folder(source.parent)
    return source.parent / folder if folder else None


def _load_cameras(path: Path, **kwargs) -> list[Camera]:
    if path.is_dir():
        source = camera_source(path)
        return load_colmap(source) if source.is_dir() else _load_cameras(source, **kwargs)
    if not path.exists():
        raise CameraFileError(f"{path}: camera file not found")
    name = path.name
    if name == "poses_bounds.npy":
        # sized and named by the images beside it where a folder holds one per pose
        return load_llff(path.parent, **(kwargs or {"image_dir": photo_folder(path.parent)}))
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


def load_nerf_transforms(
    path: str | Path, width: int | None = None, height: int | None = None
) -> list[Camera]:
    """NeRF/Blender `transforms.json`: camera-to-world in OpenGL axes (x right, y up, z back),
    as a 4x4 or a 3x4 matrix.

    Focal length from `fl_x`/`fl_y` or `camera_angle_x`; size from `w`/`h` (top level or per
    frame) unless given.
    """
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CameraFileError(f"{path}: not a readable JSON file ({exc})") from exc
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        kind = {"NoneType": "nothing", "list": "an empty list"}.get(
            type(frames).__name__, f"a value of type {type(frames).__name__}"
        )
        raise CameraFileError(f"{path}: 'frames' must be a non-empty list of frames, got {kind}")
    check_count(len(frames), path)
    cams = []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise CameraFileError(f"{path}: frame {i} is a {type(frame).__name__}, not an object")
        info = {**meta, **frame}
        w = width or info.get("w")
        h = height or info.get("h")
        if w is None or h is None:
            raise CameraFileError(
                f"{path}: frame {i} has no image size ('w'/'h'); pass width/height"
            )
        w, h = (_size(info, key, v, path, i) for key, v in (("w", w), ("h", h)))
        if "fl_x" in info:
            fx = _number(info, "fl_x", path, i)
            fy = _number(info, "fl_y", path, i) if "fl_y" in info else fx
        elif "camera_angle_x" in info:
            fx = 0.5 * w / np.tan(0.5 * field_of_view(info, "camera_angle_x", path, i))
            fy = fx
            if "camera_angle_y" in info:
                fy = 0.5 * h / np.tan(0.5 * field_of_view(info, "camera_angle_y", path, i))
        else:
            raise CameraFileError(f"{path}: frame {i} has no focal length (fl_x or camera_angle_x)")
        cx = _number(info, "cx", path, i) if "cx" in info else w / 2.0
        cy = _number(info, "cy", path, i) if "cy" in info else h / 2.0
        if "transform_matrix" not in frame:
            raise CameraFileError(f"{path}: frame {i} has no transform_matrix")
        c2w = pose_matrix(frame["transform_matrix"], path, i)
        c2w[:3, 1:3] *= -1.0  # OpenGL -> OpenCV axes
        name = Path(str(frame.get("file_path", f"frame_{i:05d}"))).stem
        w2c = invert_pose(c2w, path, name)
        cams.append(checked_camera(intrinsics(fx, fy, cx, cy), w2c, w, h, name, path))
    return cams


def _number(info: dict, key: str, path: Path, frame: int) -> float:
    value = info[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CameraFileError(f"{path}: frame {frame}: {key}={value!r} is not a number")
    return float(value)


def _size(info: dict, key: str, value, path: Path, frame: int) -> int:
    from sagonline.scene.cameras import whole_pixels

    try:
        return whole_pixels(value, f"frame {frame}: {key}")
    except ValueError as exc:
        raise CameraFileError(f"{path}: {exc}") from None


def pose_matrix(value, path: Path, frame: int) -> np.ndarray:
    """A camera-to-world pose as 4x4 (a 3x4 one gets its [0, 0, 0, 1] row)."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraFileError(
            f"{path}: frame {frame}: transform_matrix is not a matrix of numbers"
        ) from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        shape = "x".join(map(str, m.shape)) or "a scalar"
        raise CameraFileError(
            f"{path}: frame {frame}: transform_matrix is {shape}; expected 4x4 or 3x4"
        )
    return m


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
    check_count(len(entries), path)
    cams = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise CameraFileError(f"{path}: camera {i} is a {type(e).__name__}, not an object")
        missing = [k for k in ("rotation", "position", "fx", "fy", "width", "height") if k not in e]
        if missing:
            raise CameraFileError(f"{path}: camera {i} lacks {missing}")
        c2w = np.eye(4)
        c2w[:3, :3] = np.asarray(e["rotation"], dtype=np.float64)
        c2w[:3, 3] = np.asarray(e["position"], dtype=np.float64)
        w, h = (_size(e, k, e[k], path, i) for k in ("width", "height"))
        K = intrinsics(_number(e, "fx", path, i), _number(e, "fy", path, i), w / 2.0, h / 2.0)
        name = str(e.get("img_name", i))
        cams.append(checked_camera(K, invert_pose(c2w, path, name), w, h, name, path))
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
    from sagonline.core.files import atomic_write_text

    return atomic_write_text(path, json.dumps(entries, indent=1))


def load_npz_cameras(path: str | Path) -> list[Camera]:
    """A `.npz` with `viewmats` (N, 4, 4) world-to-camera, `Ks` (N, 3, 3), `width`, `height`."""
    path = Path(path)
    z = np.load(path)
    for key in ("viewmats", "Ks", "width", "height"):
        if key not in z:
            raise CameraFileError(f"{path}: missing array {key!r}")
    check_count(len(z["Ks"]), path)
    return [
        make_camera(K, vm, int(z["width"]), int(z["height"]), f"{i:05d}")
        for i, (K, vm) in enumerate(zip(z["Ks"], z["viewmats"], strict=True))
    ]
