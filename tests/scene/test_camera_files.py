"""Camera files: poses_bounds, transforms.json and COLMAP models that are damaged, singular,
duplicated or too large are refused naming the file and the field."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from sagonline.scene.io.cameras import CameraFileError, load_cameras
from tests.fixtures import (
    llff_scene,
)
from tests.refusals import NAMES, eval_generic, generic_capture


def test_pixel_ceiling_names_itself():
    from sagonline.scene.cameras import MAX_PIXELS, intrinsics, make_camera

    with pytest.raises(ValueError, match=r"MAX_PIXELS.*SAGONLINE_MAX_PIXELS"):
        make_camera(intrinsics(10, 10, 5, 5), np.eye(4), 100_000, MAX_PIXELS // 100_000 + 1)


def test_random_bytes_as_poses_bounds_name_the_file(tmp_path, capsys):
    root = generic_capture(tmp_path / "cap")
    (root / "poses_bounds.npy").write_bytes(os.urandom(2000))
    with pytest.raises(SystemExit):
        eval_generic(tmp_path, tmp_path / "run")
    err = capsys.readouterr().err
    assert "poses_bounds.npy" in err and "not a readable .npy" in err


def test_singular_llff_pose_names_the_frame(tmp_path):
    """Named by its photograph (the poses take the names of images_4/ beside them)."""
    llff_scene(tmp_path, NAMES, with_scene=False)
    arr = np.load(tmp_path / "poses_bounds.npy")
    arr[2, :15] = 0.0
    arr[2, [4, 9, 14]] = [24, 32, 30]  # keep h, w, f
    np.save(tmp_path / "poses_bounds.npy", arr)
    with pytest.raises(CameraFileError, match="frame 'IMG_0002' has a singular pose"):
        load_cameras(tmp_path / "poses_bounds.npy")


def test_duplicate_camera_names_are_refused(tmp_path, capsys):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras
    from tests.fixtures import orbit_cameras, write_nerf_transforms

    cams = orbit_cameras(4)
    write_nerf_transforms(tmp_path / "t.json", cams, ["a", "b", "a", "c"])
    with pytest.raises(CameraFileError, match="frames 0 and 2 are both named 'a'"):
        load_cameras(tmp_path / "t.json")


def _transforms(tmp_path, **changes):
    from tests.fixtures import orbit_cameras, write_nerf_transforms

    path = write_nerf_transforms(tmp_path / "transforms.json", orbit_cameras(3))
    meta = json.loads(path.read_text())
    for key, value in changes.items():
        if key == "matrix3x4":
            for f in meta["frames"]:
                f["transform_matrix"] = f["transform_matrix"][:3]
        else:
            meta[key] = value
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"fl_x": "500"}, "fl_x='500' is not a number"),
        ({"w": True}, "is not a whole number of pixels"),
        ({"w": 32.5}, "is not a whole number of pixels"),
        (
            {"frames": {"a": 1}},
            "'frames' must be a non-empty list of frames, got a value of type dict",
        ),
        ({"frames": []}, "'frames' must be a non-empty list of frames, got an empty list"),
    ],
)
def test_camera_files_are_refused_naming_the_field(tmp_path, changes, message):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras

    with pytest.raises(CameraFileError, match=message):
        load_cameras(_transforms(tmp_path, **changes))


def test_a_3x4_transform_matrix_is_read(tmp_path):
    from sagonline.scene.io.cameras import load_cameras

    full = load_cameras(_transforms(tmp_path))
    short = load_cameras(_transforms(tmp_path, matrix3x4=True))
    for a, b in zip(full, short, strict=True):
        assert np.allclose(a.world_to_cam, b.world_to_cam)


def test_colmap_models_missing_images_or_with_a_zero_quaternion(tmp_path):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras
    from tests.fixtures import orbit_cameras, write_colmap_text

    write_colmap_text(tmp_path / "m", orbit_cameras(3))
    assert len(load_cameras(tmp_path / "m")) == 3
    lines = (tmp_path / "m" / "images.txt").read_text().splitlines()
    data = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")]
    parts = lines[data[0]].split()
    parts[1:5] = ["0", "0", "0", "0"]
    lines[data[0]] = " ".join(parts)
    (tmp_path / "m" / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(CameraFileError, match="no rotation"):
        load_cameras(tmp_path / "m")
    (tmp_path / "m" / "images.txt").unlink()
    with pytest.raises(CameraFileError, match="without images.bin or images.txt"):
        load_cameras(tmp_path / "m")


def test_a_camera_file_beyond_the_ceiling_is_refused_quickly(tmp_path):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras
    from sagonline.scene.io.pose import MAX_CAMERAS

    one = {"transform_matrix": np.eye(4).tolist(), "file_path": "x"}
    meta = {"fl_x": 50, "w": 64, "h": 48, "frames": [one] * (MAX_CAMERAS + 1)}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(CameraFileError, match="exceed the ceiling of 20,000"):
        load_cameras(tmp_path / "transforms.json")


def _nerf(path: Path, **changes) -> Path:
    frame = {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"camera_angle_x": 0.8, "w": 32, "h": 24, "frames": [frame]}
    for key, value in changes.items():
        (frame if key == "transform_matrix" else meta)[key] = value
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"transform_matrix": np.full((4, 4), np.nan).tolist()}, "NaN/Inf"),
        ({"camera_angle_x": 0.0}, "not a pinhole field of view"),
        ({"camera_angle_x": float(np.pi)}, "not a pinhole field of view"),
        ({"transform_matrix": np.zeros((4, 4)).tolist()}, "frame 'a' has a singular pose"),
        ({"transform_matrix": (2 * np.eye(4)).tolist()}, "not a rotation"),
        ({"transform_matrix": np.eye(3).tolist()}, "is 3x3; expected 4x4 or 3x4"),
        ({"camera_angle_x": "wide"}, ""),
        ({"w": 0}, "not positive"),
        ({"w": -32}, "not positive"),
    ],
)
def test_bad_cameras_name_the_file(tmp_path, change, message):
    path = _nerf(tmp_path / "transforms.json", **change)
    with pytest.raises(CameraFileError, match=rf"transforms\.json: .*{message}"):
        load_cameras(path)


def test_nerf_file_under_another_name_loads(tmp_path):
    cams = load_cameras(_nerf(tmp_path / "poses_for_my_scene.json"))
    assert len(cams) == 1 and cams[0].width == 32
    assert torch.isfinite(cams[0].K).all()
