"""Sparse points from posed images: they land on the surfaces the images show."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from sagonline.core.files import atomic_write_image
from sagonline.fitting.triangulate import triangulate_known_poses
from sagonline.render.api import to_uint8
from sagonline.render.rasterize import rasterize
from sagonline.scene.generator import make_scene


@pytest.mark.slow
def test_points_land_on_the_synthetic_surfaces(tmp_path):
    s = make_scene(layout="forward", num_gaussians=30000, width=320, height=240, num_train_views=8)
    paths = {}
    for cam in s.train_cameras:
        paths[cam.name] = atomic_write_image(
            tmp_path / f"{cam.name}.png", to_uint8(rasterize(s.gaussians, cam).rgb)
        )
    xyz, rgb, summary = triangulate_known_poses(s.train_cameras, paths)
    assert summary["points"] == len(xyz) >= 200
    again, _, _ = triangulate_known_poses(s.train_cameras, paths)  # single-threaded, seeded
    assert np.array_equal(again, xyz)
    assert summary["mean_reprojection_error_px"] < 1.5
    assert rgb.shape == xyz.shape and rgb.min() >= 0 and rgb.max() <= 1
    # distance to the nearest surfel centre, against the scene's size
    dist, _ = cKDTree(s.gaussians.means.numpy()).query(xyz)
    size = float(np.ptp(s.gaussians.means.numpy(), axis=0).max())
    assert np.median(dist) < 0.01 * size
    assert np.mean(dist < 0.03 * size) > 0.9
    # the same cameras with a wrong pose give points off the surfaces, or none
    shifted = [
        type(c)(c.K, c.world_to_cam.clone(), c.width, c.height, c.name) for c in s.train_cameras
    ]
    for c in shifted[1::2]:
        c.world_to_cam[0, 3] += 0.05 * size
    bad, _, _ = triangulate_known_poses(shifted, paths, num_threads=2)
    if len(bad):
        assert np.median(cKDTree(s.gaussians.means.numpy()).query(bad)[0]) > 5 * np.median(dist)


@pytest.mark.slow
def test_a_lower_peak_threshold_finds_more_points_on_dim_surfaces(tmp_path):
    """The same views at a quarter of their brightness (a dark, plain object): COLMAP's
    default SIFT threshold finds few features there; `peak_threshold` 0.002 more, still on the
    surfaces; guided matching adds matches."""
    s = make_scene(layout="forward", num_gaussians=20000, width=240, height=180, num_train_views=6)
    paths = {}
    for cam in s.train_cameras:
        dim = (rasterize(s.gaussians, cam).rgb * 0.25).clamp(0, 1)
        paths[cam.name] = atomic_write_image(tmp_path / f"{cam.name}.png", to_uint8(dim))
    default, _, _ = triangulate_known_poses(s.train_cameras, paths)
    low, _, summary = triangulate_known_poses(s.train_cameras, paths, peak_threshold=0.002)
    guided, _, _ = triangulate_known_poses(
        s.train_cameras, paths, peak_threshold=0.002, guided_matching=True
    )
    assert len(low) >= 50 and len(low) > 1.5 * len(default) and len(guided) >= len(low)
    size = float(np.ptp(s.gaussians.means.numpy(), axis=0).max())
    assert np.median(cKDTree(s.gaussians.means.numpy()).query(low)[0]) < 0.01 * size
    assert summary["mean_reprojection_error_px"] < 1.5


def test_the_start_points_cache_key_names_the_detector_settings_only_off_their_defaults():
    from sagonline.fitting import FitConfig
    from sagonline.fitting.capture import detector_key

    assert detector_key(FitConfig()) == ""  # points cached before the settings stay valid
    low = detector_key(FitConfig(sift_peak_threshold=0.002))
    guided = detector_key(FitConfig(guided_matching=True))
    assert low and guided and low != guided
    with pytest.raises(ValueError, match="sift_peak_threshold"):
        FitConfig(sift_peak_threshold=0)


def test_needs_two_views(tmp_path):
    s = make_scene(layout="forward", num_gaussians=500, width=32, height=24, num_train_views=2)
    with pytest.raises(ValueError, match="at least two"):
        triangulate_known_poses(s.train_cameras[:1], {}, num_threads=1)


def test_a_machine_without_pycolmap_fits_from_cached_start_points_or_says_why(
    tmp_path, monkeypatch
):
    """A GPU machine without a registry may have no pycolmap: a fit there reads the start
    points a fit of the same views and seed cached (what `make gpu-bundle` carries); without
    them, `auto` starts from random points and says why, and `triangulate` is refused naming
    pycolmap."""
    from sagonline.core import store
    from sagonline.core.errors import DatasetError
    from sagonline.fitting import FitConfig
    from sagonline.fitting.capture import initial_points
    from sagonline.fitting.start_points import split_views

    s = make_scene(layout="forward", num_gaussians=500, width=32, height=24, num_train_views=4)
    cams = s.train_cameras
    images = {c.name: tmp_path / f"{c.name}.png" for c in cams}
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # `import pycolmap` raises ImportError
    out, shared = tmp_path / "gaussians-gpu", tmp_path / "gaussians"

    points, init = initial_points(FitConfig(init="auto"), tmp_path, cams, images, out, [shared])
    assert points is None and init == "random in frusta (no pycolmap)"
    with pytest.raises(DatasetError, match=r"needs pycolmap.*init_points\.store"):
        initial_points(FitConfig(init="triangulate"), tmp_path, cams, images, out, [shared])

    train, _ = split_views(cams, FitConfig().holdout_every, FitConfig().train_every)
    xyz = np.random.default_rng(0).random((150, 3)).astype(np.float32)
    key = ",".join(cams[i].name for i in train) + "|seed=0"
    shared.mkdir()
    store.save(shared / "init_points.store", {"xyz": xyz, "rgb": xyz, "views": key})
    (got, _), init = initial_points(FitConfig(init="auto"), tmp_path, cams, images, out, [shared])
    assert np.array_equal(got, xyz) and "cached in gaussians" in init


def test_a_fit_shares_the_start_points_any_other_fit_of_its_views_and_seed_triangulated(
    tmp_path, monkeypatch
):
    """Another recipe's fit (the paper recipe's probe after the check's fit) reads the points a
    sibling fit of the same views and seed cached, the default recipe's first; another seed's
    points are not taken."""
    from bench.runners.scenes import other_fits
    from sagonline.core import store
    from sagonline.fitting import FitConfig
    from sagonline.fitting.capture import initial_points
    from sagonline.fitting.start_points import split_views

    for name in ("gaussians-seed1", "gaussians-gpu", "gaussians-paper_probe", "gaussians"):
        (tmp_path / name).mkdir()
    (tmp_path / "gaussians-notes.txt").write_text("")  # not a folder
    out = tmp_path / "gaussians-paper_probe"
    assert [p.name for p in other_fits(out, seed=0)] == [
        "gaussians",
        "gaussians-gpu",
        "gaussians-seed1",
    ]
    assert other_fits(tmp_path / "gaussians-x-seed1", seed=1)[0].name == "gaussians-seed1"

    s = make_scene(layout="forward", num_gaussians=500, width=32, height=24, num_train_views=4)
    cams = s.train_cameras
    images = {c.name: tmp_path / f"{c.name}.png" for c in cams}
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # no triangulation: the cache or nothing
    train, _ = split_views(cams, FitConfig().holdout_every, FitConfig().train_every)
    views = ",".join(cams[i].name for i in train)
    xyz = np.random.default_rng(0).random((150, 3)).astype(np.float32)
    store.save(
        tmp_path / "gaussians-seed1" / "init_points.store",
        {"xyz": -xyz, "rgb": xyz, "views": views + "|seed=1"},
    )
    store.save(
        tmp_path / "gaussians-gpu" / "init_points.store",
        {"xyz": xyz, "rgb": xyz, "views": views + "|seed=0"},
    )
    (got, _), init = initial_points(FitConfig(), tmp_path, cams, images, out, other_fits(out, 0))
    assert np.array_equal(got, xyz) and "cached in gaussians-gpu" in init
