"""Camera conventions checked on real files, and trajectories."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from sagonline.scene.io import read_scene
from sagonline.scene.io.cameras import (
    CameraFileError,
    load_cameras,
    load_colmap,
    load_llff,
    load_nerf_transforms,
    load_npz_cameras,
    read_colmap_points,
    write_3dgs_cameras_json,
)
from sagonline.scene.trajectory import pseudo_temporal_order, smooth_path
from tests.fixtures import shared_data, small_camera


def _inside(cam, pts):
    uv, z = cam.project(torch.as_tensor(pts, dtype=torch.float32))
    return (
        (
            (z > 0)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < cam.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < cam.height)
        )
        .float()
        .mean()
        .item()
    )


def test_fern_colmap_points_project_inside_llff_views():
    fern = shared_data("llff_fern")
    cams = load_llff(fern, image_dir="images_8")
    assert len(cams) == 20 and (cams[0].width, cams[0].height) == (504, 378)
    assert cams[0].name == "image000"
    xyz, rgb = read_colmap_points(fern / "sparse" / "0")
    assert xyz.shape == (10091, 3) and rgb.dtype == np.uint8
    fractions = [_inside(c, xyz) for c in cams]
    assert min(fractions) > 0.9, fractions
    # A flipped axis convention would put most points behind or outside.
    flipped = cams[0].world_to_cam.clone()
    flipped[1] *= -1
    flipped[2] *= -1
    from dataclasses import replace

    assert _inside(replace(cams[0], world_to_cam=flipped), xyz) < 0.1


def test_garden_points_land_inside_real_cameras():
    z = np.load(shared_data("garden_points", "test_garden.npz"))
    cams = load_npz_cameras(shared_data("garden_points", "test_garden.npz"))
    assert len(cams) == 3 and (cams[0].width, cams[0].height) == (648, 420)
    for cam in cams:
        assert _inside(cam, z["means3d"]) > 0.3


def test_donut_is_centred_in_its_transforms_camera():
    cam = load_nerf_transforms(shared_data("donut_3dgs", "transforms.json"))[0]
    g = read_scene(shared_data("donut_3dgs", "point_cloud.ply"))
    uv, depth = cam.project(g.means)
    assert (depth > 0).all()
    centre = uv.mean(0)
    assert abs(centre[0] - cam.width / 2) < 0.1 * cam.width
    assert abs(centre[1] - cam.height / 2) < 0.3 * cam.height
    assert _inside(cam, g.means) > 0.999


def test_colmap_text_and_binary_through_pycolmap(tmp_path):
    import pycolmap

    (tmp_path / "cameras.txt").write_text("1 PINHOLE 64 48 50 51 32 24\n")
    (tmp_path / "images.txt").write_text(
        "2 1 0 0 0 0 0 4 1 b.png\n\n1 0.9238795 0 0.3826834 0 0.5 0 4 1 a.png\n\n"
    )
    (tmp_path / "points3D.txt").write_text("")
    cams = load_colmap(tmp_path)
    assert [c.name for c in cams] == ["a", "b"]
    assert cams[1].center.tolist() == pytest.approx([0, 0, -4], abs=1e-6)
    assert cams[0].K[1, 1].item() == 51
    binary = tmp_path / "bin"
    binary.mkdir()
    pycolmap.Reconstruction(str(tmp_path)).write_binary(str(binary))
    again = load_cameras(binary)
    for a, b in zip(cams, again, strict=True):
        assert torch.allclose(a.world_to_cam, b.world_to_cam, atol=1e-6)


def test_3dgs_cameras_json_round_trip(tmp_path):
    cams = [small_camera(name="b", eye=(1, -3, 1)), small_camera(name="a")]
    path = write_3dgs_cameras_json(tmp_path / "cameras.json", cams)
    back = load_cameras(path)
    assert [c.name for c in back] == ["a", "b"]
    assert torch.allclose(back[1].world_to_cam, cams[0].world_to_cam, atol=1e-5)


def test_transforms_json_errors(tmp_path):
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [{"file_path": "x"}]}))
    with pytest.raises(CameraFileError, match="transforms.json"):
        load_cameras(tmp_path / "transforms.json")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CameraFileError, match="empty: no cameras found"):
        load_cameras(empty)


def test_llff_cameras_take_the_size_and_names_of_the_images_beside_them(tmp_path):
    """Full-resolution poses (64x48) with images_2/, images_4/ and masks_2/ of one image per pose
    and images_8/ of fewer: the most downsampled photographs size and name the cameras, and are
    among the cameras' input files; without them, the masks (the NeRD captures' layout); with
    no folder of one image per pose, the poses' own size and numbers."""
    from sagonline.scene.io.cameras import camera_input_files
    from sagonline.scene.views import load_views
    from tests.fixtures import orbit_cameras, write_image, write_poses_bounds

    write_poses_bounds(tmp_path / "poses_bounds.npy", orbit_cameras(3, 64, 48))
    folders = (("images_2", 2, 3), ("images_4", 4, 3), ("images_8", 8, 2), ("masks_2", 2, 3))
    for folder, factor, count in folders:
        for i in range(count):
            write_image(tmp_path / folder / f"IMG_{i}.png", np.zeros((48 // factor, 64 // factor)))
    cams = load_cameras(tmp_path)
    assert [(c.name, c.width, c.height) for c in cams] == [(f"IMG_{i}", 16, 12) for i in range(3)]
    full = load_llff(tmp_path)
    assert (full[1].name, full[1].width) == ("00001", 64)
    assert torch.allclose(cams[1].K[:2], full[1].K[:2] / 4)
    assert camera_input_files(tmp_path) == [
        tmp_path / "poses_bounds.npy",
        *(tmp_path / "images_4" / f"IMG_{i}.png" for i in range(3)),
    ]
    assert "sized and named by the images of its images_4/" in load_views(tmp_path).source
    for folder in ("images_2", "images_4"):
        (tmp_path / folder / "IMG_2.png").unlink()
    cams = load_cameras(tmp_path / "poses_bounds.npy")
    assert [(c.name, c.width) for c in cams] == [(f"IMG_{i}", 32) for i in range(3)]
    assert "the images of its masks_2/" in load_views(tmp_path).source
    (tmp_path / "masks_2" / "IMG_2.png").unlink()
    cams = load_cameras(tmp_path / "poses_bounds.npy")
    assert [(c.name, c.width) for c in cams] == [(f"{i:05d}", 64) for i in range(3)]
    assert camera_input_files(tmp_path) == [tmp_path / "poses_bounds.npy"]
    assert "sized and named" not in load_views(tmp_path).source


def test_real_llff_folders_give_cameras_at_their_images_size_and_names():
    """fern: its images_8/ (20 photographs); mold_cape: its masks_4/ (119 masks, 24 photographs
    of them), whose names the photographs share."""
    fern = load_cameras(shared_data("llff_fern"))
    first = fern[0]
    assert len(fern) == 20 and (first.name, first.width, first.height) == ("image000", 504, 378)
    cape = load_cameras(shared_data("mold_cape"))
    assert len(cape) == 119 and (cape[0].name, cape[0].width) == ("IMG_5881", 912)


def test_llff_name_count_mismatch():
    with pytest.raises(CameraFileError, match="119 poses but 24 image names"):
        load_llff(shared_data("mold_cape"), image_dir="images_4")


def test_scaled_camera_intrinsics():
    cam = small_camera(40, 30)
    half = cam.scaled(20, 15)
    assert half.K[0, 0] == pytest.approx(cam.K[0, 0] / 2)
    assert half.K[1, 2] == pytest.approx(cam.K[1, 2] / 2)


def test_a_camera_already_on_the_device_is_itself():
    """`to` its own device returns the camera itself (a render calls it per view, and a new
    camera's checks read its values on the host, a wait on the GPU)."""
    cam = small_camera(40, 30)
    assert cam.to("cpu") is cam and cam.to(torch.device("cpu")) is cam


def test_pseudo_temporal_order_and_smooth_path():
    cams = [
        small_camera(name=n, eye=e)
        for n, e in [("c", (0, -4, 1)), ("a", (4, 0, 1)), ("b", (0, 4, 1))]
    ]
    assert [c.name for c in pseudo_temporal_order(cams)] == ["a", "b", "c"]
    path = smooth_path(cams, 9)
    assert len(path) == 9
    assert torch.allclose(path[0].world_to_cam, cams[0].world_to_cam, atol=1e-5)
    assert torch.allclose(path[-1].world_to_cam, cams[-1].world_to_cam, atol=1e-5)
    assert torch.allclose(path[4].world_to_cam, cams[1].world_to_cam, atol=1e-5)
    # rotations stay orthonormal and consecutive centres move smoothly
    for cam in path:
        R = cam.rotation.double()
        assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-5)
    steps = [float((a.center - b.center).norm()) for a, b in zip(path, path[1:], strict=False)]
    assert max(steps) < 2.5 * min(steps)
    looped = smooth_path(cams, 12, loop=True)
    assert len(looped) == 12


def test_smooth_path_rejects_mixed_sizes():
    with pytest.raises(ValueError, match="different image sizes"):
        smooth_path([small_camera(20, 10), small_camera(30, 10)], 4)


def test_shortest_path_order_follows_the_orbit_from_the_start():
    from sagonline.scene.trajectory import nearest_view, path_steps, shortest_path_order
    from tests.fixtures import orbit_cameras

    ring = orbit_cameras(12)
    shuffled = [ring[i] for i in np.random.default_rng(0).permutation(12)]
    start = [c.name for c in shuffled].index("v5")
    order = shortest_path_order(shuffled, start)
    assert sorted(order) == list(range(12)) and order[0] == start
    walked = [shuffled[i] for i in order]
    assert path_steps(walked).max() < 1.5 * path_steps(ring).max()  # neighbours follow
    assert path_steps(walked).sum() < 0.5 * path_steps(shuffled).sum()
    angle, dist = nearest_view(ring[:3], ring[6:])
    assert angle.shape == (3,) and angle[0] < angle[1] < angle[2]  # v0 sits next to v11
    assert float(nearest_view(ring[:1], ring[:1])[0][0]) == pytest.approx(0.0, abs=1e-3)
    assert dist.shape == (3,) and (dist > 0).all()


def test_inside_view_zero_faces_the_deepest_part_of_the_room():
    """A room seen from within (`--inside`): the views start where the most of it is seen, not
    at a near blank wall."""
    import numpy as np
    import torch

    from sagonline.scene.trajectory import orbit_around

    rng = np.random.default_rng(0)
    walls = []
    for x0, x1, y0, y1, n in (
        (-1, -1, -2, 2, 3000),
        (8, 8, -2, 2, 1000),
        (-1, 2, -2, -2, 3000),
        (-1, 2, 2, 2, 3000),
    ):
        walls.append(
            np.stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), rng.uniform(-1, 1, n)], 1)
        )
    means = torch.tensor(np.concatenate(walls), dtype=torch.float32)
    cams, line = orbit_around(means, 8, 64, 48, inside=True)
    forward = cams[0].cam_to_world[:3, 2].numpy()
    assert forward[0] > 0.9, forward  # +x: towards the far wall (the near one is 1.5 away)
    assert "view 0 faces the deepest part" in line


def test_every_nth_view_keeps_the_prompts_view_and_the_order():
    from dataclasses import replace

    from sagonline.scene.views import ViewError, every_line, segmented_views, trajectory

    cams = [replace(small_camera(), name=f"v{i:02d}") for i in range(10)]
    assert [c.name for c in segmented_views(cams, 4, keep=5)] == ["v00", "v04", "v05", "v08"]
    assert [c.name for c in segmented_views(cams, 4, keep=8)] == ["v00", "v04", "v08"]
    assert segmented_views(cams, 1, keep=3) == cams
    assert [c.name for c in segmented_views(cams, 11, keep=9)] == ["v00", "v09"]
    assert every_line(cams, 4, 5) == "4 of 10 views (every 4th, and the prompt's view 5)"
    assert every_line(cams, 2, 0) == "5 of 10 views (every 2nd)"
    assert every_line(cams, 1, 3) == "10 views"
    assert every_line(cams[:1], 1, 0) == "1 view"
    traj = trajectory(cams, every=4, keep=0, inbetween=1)
    assert [c.name for c in traj] == ["v00", "v00+1", "v04", "v04+1", "v08"]
    assert every_line(cams, 4, 0, len(traj)) == "3 of 10 views (every 4th) and 2 in between"
    assert every_line(cams, 11, 0) == "1 of 10 views (every 11th)"
    with pytest.raises(ViewError, match="--every 0"):
        segmented_views(cams, 0)
    with pytest.raises(ViewError, match="view 10 is out of range"):
        segmented_views(cams, 2, keep=10)
