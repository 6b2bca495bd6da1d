"""Fitting scenes: the loss falls, runs resume, outputs land where the adapter looks."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sagonline.core import store
from sagonline.fitting import FitConfig, SceneFitter, split_views, ssim
from sagonline.render.gsplat_backend import gsplat_available
from sagonline.render.rasterize import rasterize
from sagonline.scene.generator import make_scene
from tests.fixtures import ROOT, compose_config


@pytest.fixture(scope="module")
def views():
    s = make_scene(
        layout="forward",
        num_gaussians=2000,
        width=32,
        height=24,
        num_train_views=9,
        num_eval_views=1,
    )
    imgs = [rasterize(s.gaussians, c).rgb.clamp(0, 1) for c in s.train_cameras]
    return s.train_cameras, imgs


def tiny(**kw):
    base = dict(
        iterations=80,
        init_points=800,
        densify_from=20,
        densify_every=20,
        densify_until=60,
        sh_degree=0,
        checkpoint_every=10,
    )
    return FitConfig(**{**base, **kw})


def test_ssim_and_split():
    a = torch.rand(16, 16, 3)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    assert float(ssim(a, torch.rand(16, 16, 3))) < 0.5
    from tests.fixtures import orbit_cameras

    train, held = split_views(orbit_cameras(17), 8)
    assert len(held) == 3 and set(train).isdisjoint(held) and len(train) == 14
    sparse, same_held = split_views(orbit_cameras(17), 8, train_every=2)  # the sparse protocol
    assert same_held == held and sparse == train[::2] and len(sparse) == 7
    assert len(split_views(orbit_cameras(17), 8, train_every=9)[0]) == 2  # the fewest a fit takes
    with pytest.raises(ValueError, match="fit.train_every=14: leaves 1 training"):
        split_views(orbit_cameras(17), 8, train_every=14)


def test_the_trimmed_loss_leaves_the_worst_pixels_out_of_both_terms():
    """robust_trim: a patch no other photograph agrees with (here a painted square, 1/16 of
    the image) gets no gradient once it is among the trimmed pixels; the rest learns as
    before, and trim=0 is the plain loss."""
    from sagonline.fitting.losses import photometric_loss, trimmed_pixels

    gt = torch.rand(32, 32, 3)
    render = (gt + 0.02 * torch.randn(32, 32, 3)).clamp(0, 1).requires_grad_(True)
    photo = gt.clone()
    photo[:8, :8] = 1 - photo[:8, :8]  # what moved between photo sets
    keep = trimmed_pixels((render - photo).abs().mean(-1).detach(), 0.1)
    assert int((keep == 0).sum()) == round(0.1 * 32 * 32) and not keep[:8, :8].any()
    photometric_loss(render, photo, 0.2, trim=0.1).backward()
    grad = render.grad.abs().sum(-1)
    assert float(grad[:8, :8].max()) == 0.0 and float(grad[8:, 8:].mean()) > 0
    plain = photometric_loss(render.detach(), photo, 0.2)
    assert torch.equal(plain, photometric_loss(render.detach(), photo, 0.2, trim=0.0))
    with pytest.raises(ValueError, match="robust_trim"):
        FitConfig(robust_trim=1.0)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_loss_falls_and_densify_changes_the_count(views, kind):
    cams, imgs = views
    f = SceneFitter(tiny(kind=kind), cams, imgs)
    n0 = len(f)
    m = f.fit(progress=False)
    assert np.mean(f.history[-10:]) < 0.9 * np.mean(f.history[:10])
    assert len(f) != n0 and m["iterations"] == 80
    assert m["psnr_train"] > 12 and m["heldout_views"]
    g = f.export()
    assert g.kind == kind and torch.isfinite(g.means).all()


@pytest.mark.gpu
@pytest.mark.skipif(not gsplat_available(), reason="a fit through gsplat needs CUDA and gsplat")
@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_a_fit_on_cuda_renders_through_gsplat_and_its_loss_falls(views, kind):
    """The GPU recipe's path (gsplat's rasterizer and its backward, densification on CUDA) on
    a tiny scene, before `scripts/gpu_check.sh` spends minutes on a capture with it."""
    cams, imgs = views
    f = SceneFitter(tiny(kind=kind, device="cuda", backend="gsplat"), cams, imgs)
    n0 = len(f)
    m = f.fit(progress=False)
    assert np.mean(f.history[-10:]) < 0.9 * np.mean(f.history[:10])
    assert len(f) != n0 and m["iterations"] == 80 and m["psnr_train"] > 12
    g = f.export()
    assert g.kind == kind and torch.isfinite(g.means).all()


@pytest.mark.slow
def test_same_seed_same_scene_and_budget_stops_are_recorded(views):
    cams, imgs = views
    fits = [SceneFitter(tiny(iterations=40), cams, imgs) for _ in range(2)]
    metrics = [f.fit(progress=False) for f in fits]
    a, b = (f.export() for f in fits)
    assert metrics[0]["stopped"] == "iterations" and metrics[0]["iterations_planned"] == 40
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name  # bit for bit
    stopped = SceneFitter(tiny(iterations=40, time_budget_s=0.0), cams, imgs).fit(progress=False)
    assert stopped["stopped"] == "time_budget" and stopped["iterations"] < 40


def test_runs_on_a_budget_stopped_fit_say_so(tmp_path):
    import dataclasses

    from sagonline.datasets.synthetic import load_synthetic
    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    task = load_synthetic(
        layout="forward", num_gaussians=1500, width=40, height=30, num_train_views=5
    )[0]
    fit = {"iterations": 394, "iterations_planned": 3000, "stopped": "time_budget", "path": "x"}
    task = dataclasses.replace(task, meta={**task.meta, "fit": fit})
    with pytest.warns(UserWarning, match="after 394 of 3000 iterations"):
        report, _ = run_scene(
            task, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False)
        )
    assert report.extra["fit"]["stopped"] == "time_budget"


def test_resume_continues_where_it_stopped(views, tmp_path):
    cams, imgs = views
    ckpt = tmp_path / "fit.store"
    f = SceneFitter(tiny(iterations=20), cams, imgs)
    f.cfg = tiny(iterations=10)
    f.fit(progress=False, checkpoint=ckpt)  # an interrupted run
    state = store.load(ckpt)
    state["config"] = {**state["config"], "iterations": 20}
    store.save(ckpt, state)
    g = SceneFitter(tiny(iterations=20), cams, imgs)
    assert g.resume(ckpt) and g.step == 10
    g.fit(progress=False, checkpoint=ckpt)
    assert g.step == 20
    other = SceneFitter(tiny(iterations=31), cams, imgs)
    assert not other.resume(ckpt)


def test_a_checkpoint_older_than_a_setting_resumes_at_its_default_only(views, tmp_path):
    cams, imgs = views
    ckpt = tmp_path / "fit.store"
    f = SceneFitter(tiny(iterations=10), cams, imgs)
    f.fit(progress=False, checkpoint=ckpt)
    state = store.load(ckpt)
    state["config"].pop("depth_pseudo_every")  # written before the setting existed
    store.save(ckpt, state)
    assert SceneFitter(tiny(iterations=10), cams, imgs).resume(ckpt)
    assert not SceneFitter(tiny(iterations=10, depth_pseudo_every=2), cams, imgs).resume(ckpt)


def test_gaussians_near_cameras_are_pruned(views):
    cams, imgs = views
    f = SceneFitter(tiny(camera_clearance=0.5), cams, imgs)
    near = torch.cdist(f.params["means"].detach(), f.camera_centers).min(1).values
    assert bool((near >= 0.5).all())  # the start points already keep clear
    with torch.no_grad():  # move three Gaussians onto camera centres
        f.params["means"][:3] = f.camera_centers[:3] + 0.01
    assert f.prune_near_cameras() == 3 and f.prune_near_cameras() == 0
    off = SceneFitter(tiny(), cams, imgs)
    with torch.no_grad():
        off.params["means"][:3] = off.camera_centers[:3]
    assert off.prune_near_cameras() == 0  # clearance 0: off


def test_footprints_in_front_of_a_views_near_depth(views):
    from sagonline.fitting.strategy import in_front_of_view

    cam = views[0][0]
    ahead = cam.center + cam.rotation[2] * 1.0  # on the optical axis, 1.0 in front
    right = cam.rotation[0]  # the camera's x axis in the world
    behind = cam.center - cam.rotation[2] * 1.0
    beside = ahead + right * 50.0  # far outside the image at that depth
    means = torch.stack([ahead, ahead, behind, beside, beside])
    radius = torch.tensor([0.0, 0.0, 0.0, 0.0, 60.0])  # the last one's disc reaches the image
    hit = in_front_of_view(means, radius, cam, depth=1.5)
    assert hit.tolist() == [True, True, False, False, True]
    assert not in_front_of_view(means, radius, cam, depth=0.9).any()  # all beyond the depth


def test_view_clearance_prunes_floaters_only_where_a_view_records_depth(views):
    cams, imgs = views
    names = [c.name for c in cams]
    cfg = tiny(view_clearance=0.85, densify_from=10_000)
    f = SceneFitter(cfg, cams, imgs, view_near={n: 2.0 for n in names})
    trained = [cams[i] for i in f.train_idx]
    with torch.no_grad():  # a floater 0.5 in front of a training view, at that view's centre
        f.params["means"][:1] = trained[0].center + trained[0].rotation[2] * 0.5
        f.params["log_scales"][:1] = -6.0
    n = len(f)
    assert f.prune_near_cameras() >= 1 and len(f) < n
    kept = f.params["means"].detach()
    assert not bool(((kept - trained[0].center).norm(dim=1) < 0.51).any())
    # no recorded depth: nothing to go by, nothing pruned
    g = SceneFitter(cfg, cams, imgs)
    with torch.no_grad():
        g.params["means"][:1] = trained[0].center + trained[0].rotation[2] * 0.5
    assert g.prune_near_cameras() == 0
    with pytest.raises(ValueError, match="view_clearance_views"):
        SceneFitter(tiny(view_clearance_views="some"), cams, imgs)


def test_pose_view_clearance_prunes_only_in_front_of_pose_only_views(views):
    """After the fit, a floater at 0.3 x the near depth of a view without a photograph goes;
    one at 0.7 x (possibly the object) stays, as does everything with the rule off."""
    from sagonline.fitting.strategy import clear_of_pose_views

    cams, imgs = views
    pose = cams[-1]  # a camera of the capture with no image
    axis = pose.rotation[2]
    means = torch.stack([pose.center + axis * 0.6, pose.center + axis * 1.4])  # near: 2.0
    log_scales = torch.full((2, 3), -6.0)
    keep = clear_of_pose_views(means, log_scales, [(pose, 2.0)], fraction=0.5)
    assert keep.tolist() == [False, True]
    assert clear_of_pose_views(means, log_scales, [(pose, 2.0)], fraction=0.0).all()
    # the fitter runs it once, after its last iteration, on the pose-only cameras alone
    f = SceneFitter(
        tiny(iterations=2, densify_from=10_000, view_clearance=0.0),
        cams[:-1],
        imgs[:-1],
        other_cameras=[pose],
        view_near={pose.name: 2.0},
    )
    with torch.no_grad():
        f.params["means"][:1] = pose.center + axis * 0.6
        f.params["log_scales"][:1] = -6.0
    n = len(f)
    metrics = f.fit(progress=False)
    assert metrics["pruned_pose_views"] >= 1 and len(f) <= n - 1
    with pytest.raises(ValueError, match="pose_view_clearance"):
        tiny(pose_view_clearance=1.5)


def test_near_depths_of_views_from_llff_bounds_or_points(tmp_path):
    from sagonline.fitting.capture import view_near_depths
    from sagonline.scene.io.cameras import load_llff
    from tests.fixtures import llff_scene

    names = [f"IMG_{i:04d}" for i in range(5)]
    cams, _ = llff_scene(tmp_path / "cap", names, with_scene=False)
    rows = np.load(tmp_path / "cap" / "poses_bounds.npy")
    llff = load_llff(tmp_path / "cap", names=names)
    near = view_near_depths(tmp_path / "cap", llff, None)
    assert near == {n: pytest.approx(float(r[15])) for n, r in zip(names, rows, strict=True)}
    # no bounds file: the 2nd percentile of the points' depths inside each image
    (tmp_path / "cap" / "poses_bounds.npy").unlink()
    cam = llff[0]
    depths = torch.linspace(2.0, 4.0, 50)
    xyz = (cam.center + depths[:, None] * cam.rotation[2]).numpy()
    near = view_near_depths(tmp_path / "cap", [cam], (xyz, None))
    assert near[cam.name] == pytest.approx(float(torch.quantile(depths, 0.02)), rel=1e-4)
    assert view_near_depths(tmp_path / "cap", [cam], (xyz[:5], None)) == {}  # too few points


def test_the_capture_points_lower_an_llff_bound_that_lies_beyond_the_object(tmp_path):
    """A bound computed from some other point set can lie beyond a small object in front of
    the background (mother_child's IMG_0977: near 4.65, the statuette at 3.7): the view's near
    depth is then its own points', so the view clearance never prunes the object."""
    from sagonline.fitting.capture import view_near_depths
    from sagonline.scene.io.cameras import load_llff
    from tests.fixtures import llff_scene

    names = [f"IMG_{i:04d}" for i in range(3)]
    llff_scene(tmp_path / "cap", names, with_scene=False)
    rows = np.load(tmp_path / "cap" / "poses_bounds.npy")
    cams = load_llff(tmp_path / "cap", names=names)
    cam = cams[0]
    bound = float(rows[0, 15])
    nearer = torch.linspace(0.6 * bound, 2.0 * bound, 60)  # the object, in front of the bound
    xyz = (cam.center + nearer[:, None] * cam.rotation[2]).numpy()
    near = view_near_depths(tmp_path / "cap", [cam], (xyz, None))
    assert near[cam.name] == pytest.approx(float(torch.quantile(nearer, 0.02)), rel=1e-4)
    farther = (cam.center + (nearer + 2 * bound)[:, None] * cam.rotation[2]).numpy()
    assert view_near_depths(tmp_path / "cap", [cam], (farther, None))[cam.name] == pytest.approx(
        bound
    )  # points beyond the bound leave it


def test_a_lower_near_quantile_keeps_a_small_object_in_front_of_the_view_clearance(tmp_path):
    """The object covers 1% of a view's start points, in front of the background: at the 2nd
    percentile the view's near depth is the background's and the clearance would prune the
    object; `fit.view_near_quantile=0.005` puts it at the object."""
    from sagonline.fitting.capture import view_near_depths
    from sagonline.scene.io.cameras import load_llff
    from tests.fixtures import llff_scene

    llff_scene(tmp_path / "cap", ["IMG_0000"], with_scene=False)
    cam = load_llff(tmp_path / "cap", names=["IMG_0000"])[0]
    (tmp_path / "cap" / "poses_bounds.npy").unlink()  # the points' depths alone
    depths = torch.cat([torch.full((4,), 2.0), torch.linspace(5.0, 6.0, 396)])
    xyz = (cam.center + depths[:, None] * cam.rotation[2]).numpy()
    background = view_near_depths(tmp_path / "cap", [cam], (xyz, None))[cam.name]
    object_ = view_near_depths(tmp_path / "cap", [cam], (xyz, None), 0.005)[cam.name]
    assert background > 5.0 and object_ == pytest.approx(2.0, rel=1e-4)
    with pytest.raises(ValueError, match="view_near_quantile"):
        FitConfig(view_near_quantile=1.0)


def test_needle_penalty_only_acts_beyond_the_aspect_limit(views):
    cams, imgs = views
    f = SceneFitter(tiny(max_aspect=4.0), cams, imgs)
    with torch.no_grad():
        f.params["log_scales"][:] = torch.log(torch.tensor([0.02, 0.05]))  # aspect 2.5
    assert f.anisotropy_penalty().item() == 0.0
    with torch.no_grad():
        f.params["log_scales"][0] = torch.log(torch.tensor([0.01, 0.2]))  # aspect 20
    penalty = f.anisotropy_penalty()
    assert float(penalty.detach()) == pytest.approx(16.0 / len(f), rel=1e-4)
    penalty.backward()
    g = f.params["log_scales"].grad
    assert g[0, 1] > 0 > g[0, 0] and bool((g[1:] == 0).all())  # descent shortens the needle


def test_geometric_regularisers_join_the_loss_from_their_iterations(views):
    cams, imgs = views
    f = SceneFitter(
        tiny(lambda_dist=100.0, dist_from=5, lambda_normal=0.5, normal_from=10, iterations=20),
        cams,
        imgs,
    )
    plain = SceneFitter(tiny(iterations=20), cams, imgs)
    g = f.gaussians()
    loss, _, terms = f.loss(g, f.train_idx[0])
    terms = {k: float(v) for k, v in terms.items()}  # the loss keeps them on the device
    assert terms == {}  # step 0: neither has started
    assert loss.item() == plain.loss(plain.gaussians(), f.train_idx[0])[0].item()
    f.step = 5
    assert set(f.loss(g, f.train_idx[0])[2]) == {"dist"}
    f.step = 10
    loss, _, terms = f.loss(g, f.train_idx[0])
    terms = {k: float(v) for k, v in terms.items()}  # the loss keeps them on the device
    assert set(terms) == {"dist", "normal"} and terms["dist"] > 0 and terms["normal"] > 0
    photometric = plain.loss(plain.gaussians(), f.train_idx[0])[0].item()
    expected = photometric + 100.0 * terms["dist"] + 0.5 * terms["normal"]
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    f.step = 0
    metrics = f.fit(progress=False)  # through both starts, gradients and densification
    assert np.isfinite(f.history).all() and f.step == 20
    assert set(metrics["final_regularisers"]) == {"dist", "normal"}


def test_the_neighbour_consistency_joins_the_loss_from_its_iteration(views):
    cams, imgs = views
    f = SceneFitter(tiny(lambda_warp=2.0, warp_from=5, iterations=12), cams, imgs)
    plain = SceneFitter(tiny(iterations=12), cams, imgs)
    view = f.train_idx[0]
    assert len(f.neighbours[view]) == 2 and set(f.neighbours[view]) <= set(f.train_idx)
    g = f.gaussians()
    assert f.loss(g, view)[2] == {}  # before warp_from
    f.step = 5
    loss, _, terms = f.loss(g, view)
    terms = {k: float(v) for k, v in terms.items()}  # the loss keeps them on the device
    assert set(terms) == {"warp"} and terms["warp"] > 0
    photometric = plain.loss(plain.gaussians(), view)[0].item()
    assert loss.item() == pytest.approx(photometric + 2.0 * terms["warp"], rel=1e-5)
    f.step = 0
    metrics = f.fit(progress=False)
    assert np.isfinite(f.history).all() and set(metrics["final_regularisers"]) == {"warp"}


def test_bad_inputs(views):
    cams, imgs = views
    with pytest.raises(ValueError, match="kind"):
        SceneFitter(tiny(kind="nerf"), cams, imgs)
    with pytest.raises(ValueError, match="image of view"):
        SceneFitter(tiny(), cams, [imgs[0][:10]] + imgs[1:])


@pytest.mark.slow
def tiny_capture(root: Path, *overrides: str):
    """A 9-view capture with masks in `root` (images_4/, masks/, poses_bounds.npy), the
    `make scenes` config of a 12-iteration fit of it, and its adapter."""
    from sagonline.datasets.generic import PosedMasksDataset
    from tests.fixtures import llff_scene, object_mask, write_image

    names = [f"IMG_{i:04d}" for i in range(9)]
    if not (root / "images_4").is_dir():
        cams, scene = llff_scene(root, names, with_scene=False)
        for cam, n in zip(cams, names, strict=True):
            img = (rasterize(scene.gaussians, cam).rgb.clamp(0, 1).numpy() * 255).astype(np.uint8)
            write_image(root / "images_4" / f"{n}.JPG", img[..., ::-1])
            write_image(
                root / "masks" / f"{n}.png", (object_mask(scene, cam) > 0).astype(np.uint8) * 255
            )
    cfg = compose_config(
        "scenes",
        *[
            "dataset=generic",
            f"dataset.root={root}",
            "progress=false",
            "fit.iterations=12",
            "fit.init_points=500",
            "fit.densify_from=5",
            "fit.densify_every=5",
            "fit.densify_until=10",
            "fit.sh_degree=0",
            *overrides,
        ],
    )
    return cfg, PosedMasksDataset(root, mask_dir="masks")


def test_make_scenes_writes_where_the_adapter_looks(tmp_path, monkeypatch):
    from bench.runners.scenes import fit_scene

    cfg, adapter = tiny_capture(tmp_path / "cap")
    metrics = fit_scene(cfg, adapter, "cap")
    out = tmp_path / "cap" / "gaussians"
    saved = json.loads((out / "fit_metrics.json").read_text())
    assert saved["iterations"] == 12 and saved["psnr_heldout"] == metrics["psnr_heldout"]
    assert (out / "fit_config.json").is_file() and list(out.glob("heldout_*.png"))
    # the held-out view has a mask, so the PSNR on the object is reported beside the full one
    assert isinstance(saved["psnr_heldout_object"], float)
    assert saved["init"].startswith(("triangulated", "random"))
    # clearance resolved from the LLFF near bound and recorded
    assert json.loads((out / "fit_config.json").read_text())["camera_clearance"] > 0
    task = adapter.load_scene("cap")  # the adapter now finds the fitted scene and cameras
    assert task.gaussians.kind == "2dgs" and len(task.trajectory) == 9
    again = fit_scene(cfg, adapter, "cap")
    assert again == {"scene": "cap", "skipped": True}
    from bench.tables.fits import fit_rows

    (row,) = fit_rows([tmp_path]).to_dict("records")  # `make report`'s fits table
    assert row["psnr_heldout"] == saved["psnr_heldout"] and row["iterations"] == 12
    assert row["recipe"] == (
        "iterations=12 sh_degree=0 init_points=500 densify_from=5 densify_until=10 densify_every=5"
    )


def test_a_quantile_that_changes_no_near_depth_reuses_the_seeds_fit(tmp_path, monkeypatch):
    """`fit.view_near_quantile` into a variant folder: where the near depths of every view the
    clearances use come out the same, the fit would repeat the seed's bit for bit, so that fit
    is copied (and says so); where one differs, the variant is fitted."""
    import bench.runners.scenes
    from bench.runners.scenes import fit_scene

    width = bench.runners.scenes.cpu_capability
    cfg, adapter = tiny_capture(tmp_path / "cap")
    fit_scene(cfg, adapter, "cap")
    base = tmp_path / "cap" / "gaussians"
    recorded = json.loads((base / "fit_config.json").read_text())
    del recorded["robust_from"], recorded["view_near_quantile"]  # a fit older than these
    del recorded["backdrop"]  # (it ran on black, as fit.backdrop=fixed)
    (base / "fit_config.json").write_text(json.dumps(recorded))
    near = bench.runners.scenes.fit_near_depths
    monkeypatch.setattr(  # this capture's points: the same near depth at both quantiles
        bench.runners.scenes, "fit_near_depths", lambda d, c, p, i, q: near(d, c, p, i, 0.02)
    )
    same, _ = tiny_capture(tmp_path / "cap", "variant=q1", "fit.view_near_quantile=0.01")
    copied = fit_scene(same, adapter, "cap")
    out = tmp_path / "cap" / "gaussians-q1"
    assert copied["same_fit_as"] == "gaussians"
    assert (out / "point_cloud.ply").read_bytes() == (base / "point_cloud.ply").read_bytes()
    assert json.loads((out / "fit_config.json").read_text())["view_near_quantile"] == 0.01
    assert adapter.load_scene("cap") is not None  # the copy is a finished fit of ours
    assert fit_scene(same, adapter, "cap") == {"scene": "cap", "skipped": True}

    def nearer(d, c, p, i, q):  # the photographed views' near depths move at the new quantile
        depths = near(d, c, p, i, 0.02)
        return depths | ({n: depths[n] * 0.5 for n in i if n in depths} if q != 0.02 else {})

    monkeypatch.setattr(bench.runners.scenes, "fit_near_depths", nearer)
    other, _ = tiny_capture(tmp_path / "cap", "variant=q2", "fit.view_near_quantile=0.01")
    fitted = fit_scene(other, adapter, "cap")
    assert "same_fit_as" not in fitted  # fitted, from the seed's start points
    assert fitted["init"].startswith("random") or "cached in gaussians)" in fitted["init"]
    other, _ = tiny_capture(tmp_path / "cap", "variant=q3", "fit.iterations=13")
    assert "same_fit_as" not in fit_scene(other, adapter, "cap")  # another recipe
    monkeypatch.setattr(
        bench.runners.scenes, "fit_near_depths", near
    )  # as for q1, which was copied
    seeds_width = json.loads((base / "fit_metrics.json").read_text())["cpu_capability"]
    other_width = "AVX2" if seeds_width == "AVX512" else "AVX512"  # what torch loaded with here
    monkeypatch.setattr(
        bench.runners.scenes, "cpu_capability", lambda: other_width
    )  # another width
    wider, _ = tiny_capture(tmp_path / "cap", "variant=w", "fit.view_near_quantile=0.01")
    metrics = fit_scene(wider, adapter, "cap")
    assert "same_fit_as" not in metrics and metrics["cpu_capability"] == other_width  # new draw
    monkeypatch.setattr(
        bench.runners.scenes, "cpu_capability", width
    )  # the seed's fit's width again
    recorded = json.loads((base / "fit_metrics.json").read_text())
    assert recorded["mkl_cbwr"] == "COMPATIBLE"
    del recorded["mkl_cbwr"]  # a fit before the MKL pin: another draw, not repeated
    (base / "fit_metrics.json").write_text(json.dumps(recorded))
    older, _ = tiny_capture(tmp_path / "cap", "variant=m", "fit.view_near_quantile=0.01")
    assert "same_fit_as" not in fit_scene(older, adapter, "cap")


def test_a_fit_pins_torchs_cpu_kernels_and_mkl_before_torch_loads():
    """`python -m bench.runners.scenes` runs torch's kernels at AVX2 and MKL on its COMPATIBLE
    branch (the same results on every x86 CPU, and run to run); a pin the user set stays."""
    probe = (
        "import os, bench.runners.scenes, torch; print(os.environ['ATEN_CPU_CAPABILITY'], "
        "os.environ['MKL_CBWR'], torch.backends.cpu.get_cpu_capability())"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("ATEN_CPU_CAPABILITY", "MKL_CBWR")}
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, env=env, capture_output=True, text=True
    )
    aten, mkl, runs = done.stdout.split()
    assert (aten, mkl) == ("avx2", "COMPATIBLE") and runs in ("AVX2", "DEFAULT"), done.stdout
    done = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env | {"MKL_CBWR": "AVX2,STRICT"},
    )
    assert done.stdout.split()[1] == "AVX2,STRICT"


@pytest.mark.slow
def test_scenes_cli_errors(tmp_path):
    import subprocess
    import sys

    run = tmp_path / "run"
    res = subprocess.run(
        [sys.executable, "-m", "bench.runners.scenes", "dataset=synthetic", f"hydra.run.dir={run}"],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 2 and "generated, not fitted" in res.stderr
    assert not run.exists()  # a refused command leaves no folder behind
    empty = tmp_path / "cap"
    (empty / "masks").mkdir(parents=True)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "bench.runners.scenes",
            "dataset=generic",
            f"dataset.root={tmp_path}",
            f"hydra.run.dir={run}",
        ],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 2 and "no data at" in res.stderr


def test_read_only_data_is_never_written(tmp_path, monkeypatch):
    import sagonline.datasets.fits as fits
    from sagonline.datasets.fits import output_dir

    writable = tmp_path / "rw" / "cap"
    writable.mkdir(parents=True)
    overlay = tmp_path / "overlay"
    monkeypatch.setattr(fits, "SCENES_ROOT", overlay)
    assert output_dir(writable, "generic") == writable / "gaussians"
    data = tmp_path / "ro" / "cap"
    data.mkdir(parents=True)
    data.chmod(0o555)
    try:
        out = output_dir(data, "generic")
        assert out == overlay / "generic" / "cap" / "gaussians"
        assert not (data / "gaussians").exists()
        out.mkdir(parents=True)
        (out / "point_cloud.ply").write_text("x")
        assert fits.gaussians_dir(data, "generic") == out  # the adapter finds it there
    finally:
        data.chmod(0o755)


def test_fit_recipe_names_changed_and_missing_settings():
    from dataclasses import asdict

    from bench.tables.fits import fit_recipe
    from sagonline.fitting import FitConfig

    cfg = asdict(FitConfig(seed=1, lambda_dist=1.0, device="cuda", camera_clearance=0.3))
    assert fit_recipe(cfg) == "lambda_dist=1 seed=1"  # device and clearance are not the recipe
    cfg = {k: v for k, v in asdict(FitConfig()).items() if k != "lambda_normal"}
    assert fit_recipe(cfg) == "predates: lambda_normal"  # a fit older than the setting
    assert fit_recipe(asdict(FitConfig())) == "default"


FIT_DIGEST = """
import hashlib, sys, torch
torch.set_num_threads(int(sys.argv[1]))
from sagonline.fitting import FitConfig, SceneFitter
from sagonline.render.rasterize import rasterize
from sagonline.scene.generator import make_scene
s = make_scene(layout="forward", num_gaussians=2000, width=48, height=36, num_train_views=9)
imgs = [rasterize(s.gaussians, c).rgb.clamp(0, 1) for c in s.train_cameras]
for case in sys.argv[2:]:
    kind, size = case.split("-")
    if size == "small":
        cfg = FitConfig(iterations=30, init_points=1000, densify_from=10, densify_every=10,
                        densify_until=25, sh_degree=1, kind=kind, backend="native")
    else:  # above torch's 32k-element grain, with an odd count: its ops split over threads
        cfg = FitConfig(iterations=4, init_points=39321, densify_from=100, sh_degree=1,
                        kind=kind, backend="native", max_gaussians=50000, dist_from=0,
                        normal_from=0)
    f = SceneFitter(cfg, s.train_cameras, imgs)
    f.fit(progress=False)
    g = f.export()
    h = hashlib.sha256()
    for t in (g.means, g.quats, g.scales, g.opacities, g.sh):
        h.update(t.detach().contiguous().numpy().tobytes())
    print(case, len(g), h.hexdigest())
"""


@pytest.mark.slow
def test_the_same_seed_gives_the_same_scene_on_one_and_two_threads():
    """The compiled backward sums its gradients in an order that does not depend on the thread
    count, and torch's own ops run on one thread in a fit (above 32k elements torch splits them
    over threads, and exp/sigmoid round differently in each chunk's vector tail), so a fit is
    bit-identical on any number of threads: 2DGS and 3DGS small, and 2DGS large, each fitted
    by a process on one thread and another on two."""
    import subprocess
    import sys

    from tests.fixtures import ROOT

    cases = ["2dgs-small", "3dgs-small", "2dgs-large"]
    runs = {  # both at once: a result may not depend on what else runs on the machine either
        threads: subprocess.Popen(
            [sys.executable, "-c", FIT_DIGEST, str(threads), *cases],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for threads in (1, 2)
    }
    digests = {}
    for threads, proc in runs.items():
        out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err[-2000:]
        digests[threads] = out.splitlines()
    assert [line.split()[0] for line in digests[1]] == cases
    for one, two in zip(digests[1], digests[2], strict=True):
        assert one == two, (one, two)  # the case, its Gaussians and its digest


def test_each_draw_of_the_recipe_has_a_folder_of_its_own(tmp_path):
    """seed=k (k > 0) fits into gaussians-seed<k>/, and dataset.adapter.fit=seed<k> evaluates
    it: the draws of one recipe sit side by side, none replaces another."""
    from bench.runners.scenes import variant_of
    from sagonline.datasets.fits import find_trained_scene, gaussians_dir, output_dir
    from tests.fixtures import compose_config

    assert variant_of(compose_config("scenes", "dataset=mold_cape")) == ""
    assert variant_of(compose_config("scenes", "dataset=mold_cape", "seed=2")) == "seed2"
    assert variant_of(compose_config("scenes", "dataset=mold_cape", "variant=masked")) == "masked"
    masked_draw = compose_config("scenes", "dataset=mold_cape", "variant=masked", "seed=2")
    assert variant_of(masked_draw) == "masked-seed2"
    scene = tmp_path / "cap"
    scene.mkdir()
    assert output_dir(scene, "cap", "seed2") == scene / "gaussians-seed2"
    (scene / "gaussians-seed2" / "point_cloud.ply").write_text("")
    assert gaussians_dir(scene, "cap", "seed2") == scene / "gaussians-seed2"
    assert find_trained_scene(scene, "cap", "seed2").parent.name == "gaussians-seed2"
    with pytest.raises(Exception, match="gaussians/point_cloud.ply"):
        find_trained_scene(scene, "cap")
    with pytest.raises(Exception, match=r"at .*gaussians-seed1/point_cloud.ply .*ARGS=seed=1"):
        find_trained_scene(scene, "cap", "seed1")  # the message names the draw's folder and fit


def test_a_missing_fit_of_read_only_data_is_expected_where_make_scenes_writes(
    tmp_path, monkeypatch
):
    """Shared data on a read-only disk: its fits live in the project's scenes/ overlay, and the
    refusal names that path, not one inside the data folder that nobody can write."""
    import sagonline.datasets.fits as fits

    monkeypatch.setattr(fits, "SCENES_ROOT", tmp_path / "scenes")
    scene = tmp_path / "data" / "cap"
    scene.mkdir(parents=True)
    scene.chmod(0o555)
    try:
        with pytest.raises(fits.DatasetError) as refused:
            fits.find_trained_scene(scene, "capset")
        assert (
            fits.output_dir(scene, "capset") == tmp_path / "scenes" / "capset" / "cap" / "gaussians"
        )
    finally:
        scene.chmod(0o755)
    expected = tmp_path / "scenes" / "capset" / "cap" / "gaussians" / "point_cloud.ply"
    assert f"expected {expected} ({scene} is read-only); put" in str(refused.value)
    with pytest.raises(fits.DatasetError, match=f"expected {scene}/gaussians/point_cloud.ply; put"):
        fits.find_trained_scene(scene, "capset")


def test_a_second_fit_into_the_same_folder_is_refused(tmp_path, monkeypatch):
    """Two `make scenes` of one scene and seed at once would interleave their checkpoints and
    files: the second is refused while the first holds the folder."""
    from bench.runners.scenes import fit_scene
    from sagonline.core.outputs import OutputError, RunLock

    scene = tmp_path / "cap"
    scene.mkdir()

    class Adapter:
        name = "cap"

        def capture(self, name):
            return scene, ["cam"] * 2, {"a": None, "b": None}

    cfg = compose_config("scenes", "dataset=mold_cape", "seed=1")
    refused = pytest.raises(OutputError, match="gaussians-seed1: another run is writing")
    with RunLock(scene / "gaussians-seed1"), refused:
        fit_scene(cfg, Adapter(), "cap")


def test_white_backdrop_is_detected_from_the_photographs_borders():
    """`capture.white_backdrop`: white when most photographs' borders are white; a room, a
    black render or too few white photographs are not."""
    from sagonline.fitting.capture import fitting_background, white_backdrop
    from sagonline.fitting.config import FitConfig

    def photo(border: float) -> torch.Tensor:
        im = torch.full((40, 60, 3), border)
        im[8:32, 10:50] = torch.tensor([0.6, 0.4, 0.2])  # the object, off the border
        return im

    assert white_backdrop([photo(0.97)] * 10)
    assert not white_backdrop([photo(0.5)] * 10) and not white_backdrop([photo(0.0)] * 10)
    assert not white_backdrop([photo(0.97)] * 8 + [photo(0.5)] * 2 + [photo(0.0)])  # 8 of 11
    assert not white_backdrop([])
    grey = FitConfig(background=(0.2, 0.2, 0.2), backdrop="fixed")
    assert fitting_background(grey, [photo(0.97)] * 3) == (0.2, 0.2, 0.2)  # fixed: as set
    detect = FitConfig(background=(0.2, 0.2, 0.2))  # the default: detect
    assert fitting_background(detect, [photo(0.97)] * 3) == (1.0, 1.0, 1.0)
    assert fitting_background(detect, [photo(0.3)] * 3) == (0.2, 0.2, 0.2)
    with pytest.raises(ValueError, match="backdrop"):
        FitConfig(backdrop="white")


def test_backdrop_detect_fits_on_white_only_where_the_photographs_are(tmp_path):
    """`fit.backdrop=detect` (the default) on photographs of a dark room renders on black: the
    recipe with `fit.backdrop=fixed` is its fit (copied); on the same capture photographed
    against white it fits on white, records it, and the evaluation renders that scene on
    white."""
    from bench.runners.scenes import fit_scene
    from sagonline.scene.io.images import read_rgb
    from tests.fixtures import write_image

    cfg, adapter = tiny_capture(tmp_path / "cap")
    fit_scene(cfg, adapter, "cap")
    fixed, _ = tiny_capture(tmp_path / "cap", "variant=fixed", "fit.backdrop=fixed")
    copied = fit_scene(fixed, adapter, "cap")
    assert copied["same_fit_as"] == "gaussians"  # rendered on black: nothing was detected
    recorded = json.loads((tmp_path / "cap" / "gaussians-fixed" / "fit_config.json").read_text())
    assert recorded["backdrop"] == "fixed" and recorded["background"] == [0.0, 0.0, 0.0]

    root = tmp_path / "white"
    tiny_capture(root)  # the same views, their borders made white (a studio's sweep)
    for path in (root / "images_4").iterdir():
        img = read_rgb(path).copy()
        img[:2], img[-2:], img[:, :2], img[:, -2:] = 255, 255, 255, 255
        write_image(path, img[..., ::-1])
    white, white_adapter = tiny_capture(root)
    metrics = fit_scene(white, white_adapter, "white")
    assert "same_fit_as" not in metrics
    assert json.loads((root / "gaussians" / "fit_config.json").read_text())["background"] == [
        1.0,
        1.0,
        1.0,
    ]
    assert white_adapter.load_scene("white").background == (1.0, 1.0, 1.0)

    # random backgrounds: on for the room, off where the fit renders on the detected backdrop
    for capture, path in (("cap", tmp_path / "cap"), ("white", root)):
        rnd, rnd_adapter = tiny_capture(path, "variant=rnd", "fit.random_background=true")
        fit_scene(rnd, rnd_adapter, capture)
        recorded = json.loads((path / "gaussians-rnd" / "fit_config.json").read_text())
        assert recorded["random_background"] is (capture == "cap")


def test_a_centre_a_photograph_sees_past_is_looked_through(views):
    """`looked_through`: a centre nearer than the opaque surface rendered at its pixel (by more
    than the margin) is; one at that surface, one behind it, one where the render is
    transparent and one outside the image are not."""
    from sagonline.fitting.strategy import looked_through

    cam = views[0][0]
    h, w = cam.height, cam.width
    alpha = torch.ones(h, w)
    alpha[:, : w // 2] = 0.2  # the left half: nothing opaque drawn
    depth = alpha * 4.0  # alpha-weighted: the surface at depth 4
    axis, right = cam.rotation[2], cam.rotation[0]
    centre = cam.center + axis  # depth 1 on the optical axis (the right half starts there)
    on_right = centre + right * 0.25 * float(w) / float(cam.K[0, 0])  # a quarter image right
    means = torch.stack(
        [
            on_right,  # depth 1 < 0.9 x 4: looked through
            cam.center + axis * 3.8 + (on_right - centre) * 3.8,  # at the surface (within 10%)
            cam.center + axis * 6.0 + (on_right - centre) * 6.0,  # behind it
            on_right - 2 * (on_right - centre),  # a quarter image left: transparent there
            centre + right * 100.0,  # outside the image
        ]
    )
    assert looked_through(means, cam, alpha, depth, margin=0.1).tolist() == [
        True,
        False,
        False,
        False,
        False,
    ]
    assert not looked_through(means, cam, alpha, depth, margin=0.8)[0]  # 1 > 0.2 x 4


def test_the_carve_drops_a_floater_the_photographs_look_through_and_the_polish_trains(
    views, tmp_path
):
    """carve_views: a floater put nearer than the fitted surface in the training views goes,
    the polish trains its iterations after the fit, and a resumed fit that finished does not
    carve or polish again; off (0), neither runs."""
    from sagonline.fitting.finish import carve
    from sagonline.fitting.strategy import looked_through

    cams, imgs = views
    f = SceneFitter(tiny(iterations=30, carve_views=2, polish_iterations=5), cams, imgs)
    f.fit(progress=False, checkpoint=tmp_path / "fit.store")
    assert f.finished and len(f.history) == 35  # 30 iterations, then the polish's 5
    again = SceneFitter(tiny(iterations=30, carve_views=2, polish_iterations=5), cams, imgs)
    assert again.resume(tmp_path / "fit.store") and again.finished
    again.fit(progress=False)
    assert len(again.history) == 35 and len(again) == len(f)  # not carved nor polished twice

    # a tiny floater on a training camera's axis, at a fifth of the surface's depth there
    cam = f.cams[f.train_idx[0]]
    with torch.no_grad():
        out = f.render(f.gaussians(), f.train_idx[0])
    v, u = cam.height // 2, cam.width // 2
    assert float(out.alpha[v, u]) > 0.5
    surface = float(out.depth[v, u] / out.alpha[v, u])
    floater = cam.center + cam.rotation[2] * 0.2 * surface
    with torch.no_grad():
        f.params["means"][0] = floater
        f.params["log_scales"][0] = -8.0
        out = f.render(f.gaussians(), f.train_idx[0])
    assert looked_through(floater[None], cam, out.alpha, out.depth, 0.1).item()
    f.cfg = tiny(iterations=30, carve_views=1)
    n = len(f)
    assert carve(f) >= 1 and len(f) < n
    assert not bool((f.params["means"].detach() - floater).norm(dim=1).lt(1e-6).any())

    off = SceneFitter(tiny(iterations=30), cams, imgs)
    off.fit(progress=False)
    assert off.carved == 0 and len(off.history) == 30


def test_opacity_entropy_is_zero_at_the_ends_ln2_at_a_half_and_pushes_to_the_nearer_end():
    from sagonline.fitting.losses import opacity_entropy

    ends = torch.tensor([-30.0, 30.0])
    assert float(opacity_entropy(ends)) < 1e-9
    assert float(opacity_entropy(torch.zeros(4))) == pytest.approx(math.log(2), abs=1e-6)
    logits = torch.tensor([-1.0, 0.5, 2.0], requires_grad=True)
    opacity_entropy(logits).backward()
    assert logits.grad[0] > 0 and logits.grad[1] < 0 and logits.grad[2] < 0  # descent: away from 0


def test_the_opacity_entropy_polish_makes_opacities_binary_and_drops_the_faded(views):
    """polish_opacity_entropy without the carve: the polish runs its iterations with the
    entropy in the loss, then the Gaussians below prune_opacity go (counted as faded)."""
    cams, imgs = views
    plain = SceneFitter(tiny(iterations=30, polish_iterations=20), cams, imgs)
    plain.fit(progress=False)
    assert len(plain.history) == 30 and plain.faded == 0  # 0: no polish

    f = SceneFitter(
        tiny(iterations=30, polish_iterations=20, polish_opacity_entropy=1.0), cams, imgs
    )
    f.fit(progress=False)
    assert len(f.history) == 50 and "entropy" in f.last_terms
    assert not f.polishing and f.evaluate()["faded"] == f.faded
    opacity = torch.sigmoid(f.params["opacity_logit"].detach()).flatten()
    assert float(opacity.min()) >= f.cfg.prune_opacity  # the faded ones went
    from sagonline.fitting.losses import opacity_entropy

    assert float(opacity_entropy(f.params["opacity_logit"].detach())) < float(
        opacity_entropy(plain.params["opacity_logit"].detach())
    )


@pytest.mark.parametrize(
    "bad",
    [
        {"carve_views": -1},
        {"carve_margin": 1.0},
        {"polish_iterations": -5},
        {"polish_opacity_entropy": -0.1},
        {"co_prune_seed": -1},
        {"co_prune_sigmas": 0.0},
    ],
)
def test_carve_settings_out_of_range_are_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        FitConfig(**bad)


def test_finish_from_runs_only_the_steps_after_a_finished_fit_of_the_same_recipe(tmp_path):
    """finish_from: the seed's finished fit is this recipe's state after the last iteration,
    so only the carve and polish run (into the variant's own folder; the base is untouched);
    a base fitted with another recipe is refused, naming the settings that differ."""
    from bench.runners.scenes import fit_scene
    from sagonline.core.errors import DatasetError
    from sagonline.core.provenance import digest_file

    cfg, adapter = tiny_capture(tmp_path / "cap")
    fit_scene(cfg, adapter, "cap")
    base = tmp_path / "cap" / "gaussians"
    before = digest_file(base / "point_cloud.ply")
    carve = [
        "variant=carved",
        "finish_from=default",
        "fit.carve_views=1",
        "fit.polish_iterations=3",
    ]
    cfg2, _ = tiny_capture(tmp_path / "cap", *carve)
    metrics = fit_scene(cfg2, adapter, "cap")
    out = tmp_path / "cap" / "gaussians-carved"
    assert metrics["iterations"] == 12 and "carved" in metrics
    recorded = json.loads((out / "fit_config.json").read_text())
    assert recorded["carve_views"] == 1 and digest_file(base / "point_cloud.ply") == before
    cfg3, _ = tiny_capture(tmp_path / "cap", "variant=other", *carve[1:], "fit.iterations=13")
    with pytest.raises(DatasetError, match="fit.iterations differ"):
        fit_scene(cfg3, adapter, "cap")


def test_random_backgrounds_are_drawn_per_step_and_leave_no_pixel_see_through(views):
    """random_background: each training step renders on its own colour, drawn from the seed
    and the step (so a resumed fit draws the same); the renders after the fit use
    `background`; and a photograph's black can no longer be matched by the black background
    showing through, so the fitted views end more opaque than the plain fit's."""
    cams, imgs = views
    from sagonline.fitting.capture import training_background

    plain = SceneFitter(tiny(iterations=150), cams, imgs)
    rnd = SceneFitter(tiny(iterations=150, random_background=True), cams, imgs)
    assert training_background(plain.cfg, 0) is None
    first = training_background(rnd.cfg, 0)
    assert first.shape == (3,) and bool(((first >= 0) & (first <= 1)).all())
    assert torch.equal(first, training_background(tiny(random_background=True), 0))
    assert not torch.equal(first, training_background(rnd.cfg, 1))
    torch.manual_seed(0)
    plain.fit(progress=False)
    torch.manual_seed(0)
    rnd.fit(progress=False)
    with torch.no_grad():
        g_plain, g_rnd = plain.gaussians(), rnd.gaussians()
        seen_through = [
            (1 - f.render(g, i).alpha).mean()
            for f, g in ((plain, g_plain), (rnd, g_rnd))
            for i in rnd.train_idx
        ]
    n = len(rnd.train_idx)
    assert float(sum(seen_through[n:])) < 0.95 * float(sum(seen_through[:n]))
    black = torch.zeros(3)
    with torch.no_grad():  # after the fit: the fixed background
        assert torch.equal(rnd.render(g_rnd, 0).rgb, rnd.render(g_rnd, 0, background=black).rgb)


def test_the_co_pruning_keeps_what_a_second_draw_has_near_and_polishes(views):
    """co_prune_seed: with a second draw's centres, the Gaussians none of them lies within
    co_prune_sigmas of their largest scale of go, counted; the polish then trains;
    `nearest_distances` is the brute-force minimum."""
    from sagonline.fitting.finish import co_prune, nearest_distances

    points, others = torch.rand(50, 3), torch.rand(7, 3)
    brute = (points[:, None] - others[None]).norm(dim=2).min(dim=1).values
    assert torch.allclose(nearest_distances(points, others, chunk=8), brute, atol=1e-6)

    cams, imgs = views
    f = SceneFitter(tiny(iterations=30, co_prune_seed=1, polish_iterations=4), cams, imgs)
    f.fit(progress=False)
    assert f.co_pruned == 0 and len(f.history) == 30  # no second draw given: nothing to do
    with torch.no_grad():  # ten tiny Gaussians whose centres the second draw lacks
        f.params["log_scales"][:10] = -12.0
    partner = f.params["means"].detach().clone()
    n = len(partner)
    f.cfg, f.partner_means, f.finished = tiny(iterations=30, co_prune_seed=1), partner[10:], False
    f.finish()
    assert f.co_pruned == 10 and len(f) == n - 10 and len(f.history) == 30 + 300
    assert f.evaluate()["co_pruned"] == 10
    assert co_prune(f, f.params["means"].detach().clone()) == 0  # a draw agreeing everywhere


def test_co_pruning_reads_the_other_seeds_finished_fit_and_needs_finish_from(tmp_path):
    from bench.runners.scenes import fit_scene
    from sagonline.core.errors import DatasetError

    root = tmp_path / "cap"
    for seed in (0, 1):
        cfg, adapter = tiny_capture(root, f"seed={seed}")
        fit_scene(cfg, adapter, "cap")
    copr = ["variant=copr", "fit.co_prune_seed=1", "fit.polish_iterations=2"]
    cfg, _ = tiny_capture(root, *copr, "finish_from=default")
    metrics = fit_scene(cfg, adapter, "cap")
    assert "co_pruned" in metrics and metrics["iterations"] == 12
    assert (
        json.loads((root / "gaussians-copr" / "fit_config.json").read_text())["co_prune_seed"] == 1
    )
    with pytest.raises(DatasetError, match="give finish_from"):
        fit_scene(tiny_capture(root, *copr, "variant=copr2")[0], adapter, "cap")
    same, _ = tiny_capture(root, "variant=copr3", "fit.co_prune_seed=0", "finish_from=default")
    with pytest.raises(DatasetError, match="this fit's own seed"):
        fit_scene(same, adapter, "cap")
    none, _ = tiny_capture(root, "variant=copr4", "fit.co_prune_seed=2", "finish_from=default")
    with pytest.raises(DatasetError, match="holds no fit of ours"):
        fit_scene(none, adapter, "cap")


def test_a_fit_interrupted_between_checkpoints_resumes_to_the_uninterrupted_fit(views, tmp_path):
    """Stopped at step 13 (its checkpoint at 10) and resumed, the fit draws the same training
    views from step 10 on as one that ran through (it drew others before), and densifies at 15
    and 25 from the same statistics, so both end with the same Gaussians."""
    cams, imgs = views
    cfg = tiny(iterations=30, densify_from=5, densify_every=10)
    whole = SceneFitter(cfg, cams, imgs)
    started_with = len(whole)
    whole.fit(progress=False)
    assert len(whole) != started_with  # the densification ran

    ckpt = tmp_path / "fit.store"
    cut = SceneFitter(cfg, cams, imgs)
    step_once = cut.train_step

    def interrupted(view, progress):
        if cut.step == 13:
            raise KeyboardInterrupt
        return step_once(view, progress)

    cut.train_step = interrupted
    with pytest.raises(KeyboardInterrupt):
        cut.fit(progress=False, checkpoint=ckpt)
    resumed = SceneFitter(cfg, cams, imgs)
    assert resumed.resume(ckpt) and resumed.step == 10
    resumed.fit(progress=False, checkpoint=ckpt)
    assert resumed.history == whole.history
    for name, value in whole.params.items():
        assert torch.equal(resumed.params[name], value), name
