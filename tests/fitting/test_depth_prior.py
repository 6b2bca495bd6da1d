"""The monocular depth prior of the fit (`fit.lambda_depth`): the correlation loss, the ONNX depth
model's wrapper and its refusals, and the prior inside the fitting loop."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from sagonline.fitting import FitConfig, SceneFitter
from sagonline.fitting.depth_prior import (
    DepthPriorError,
    MonocularDepth,
    between,
    depth_correlation,
    pearson,
)
from sagonline.render.api import render
from sagonline.render.rasterize import rasterize
from sagonline.scene.generator import make_scene
from tests.fixtures import ROOT, shared_data

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")


def channel_mean_model(path: Path, size: tuple | None = (16, 16)) -> Path:
    """A stand-in depth network: (1, 3, H, W) -> (1, 1, H, W), the mean of the channels."""
    from onnx import TensorProto, helper

    dims = [1, 3, *size] if size else [1, 3, "h", "w"]
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["image"], ["depth"], axes=[1], keepdims=1)],
        "channel_mean",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, dims)],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, *dims[2:]])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def surface(H: int = 64, W: int = 96) -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W) alpha-weighted depth of a tilted plane with a bump, and its (H, W) alpha."""
    ys, xs = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    z = 2 + ys + 0.5 * torch.exp(-((xs - 0.5) ** 2 + (ys - 0.5) ** 2) / 0.02)
    alpha = torch.ones(H, W)
    alpha[:, :8] = 0.1  # an uncovered strip: left out
    return z * alpha, alpha


def test_the_depth_correlation_is_zero_up_to_scale_and_shift_and_largest_reversed():
    depth, alpha = surface()
    z = depth / alpha
    same = depth_correlation(depth, alpha, 3 * z + 1, patch=16)
    assert float(same) == pytest.approx(0.0, abs=1e-5)
    reversed_ = depth_correlation(depth, alpha, -z, patch=16)
    assert float(reversed_) == pytest.approx(2.0, abs=1e-4)
    noisy = z + 0.3 * torch.randn(z.shape, generator=torch.Generator().manual_seed(0))
    assert 0 < float(depth_correlation(depth, alpha, noisy, patch=16)) < 1
    # the uncovered strip does not count, whatever the prior says there
    wild = (3 * z + 1).clone()
    wild[:, :8] = torch.rand(64, 8) * 100
    assert float(depth_correlation(depth, alpha, wild, patch=16)) < 1e-3
    # patches larger than the view: the whole view alone
    assert float(depth_correlation(depth, alpha, 3 * z + 1, patch=512)) == pytest.approx(
        0, abs=1e-5
    )


def test_patch_zero_correlates_the_whole_view_only():
    depth, alpha = surface()
    z = depth / alpha
    # each tile's own shape reversed, the tiles' order kept: the tiles disagree, the view agrees
    tiled = z.clone()
    for r in range(0, z.shape[0], 16):
        for c in range(0, z.shape[1], 16):
            block = tiled[r : r + 16, c : c + 16]
            tiled[r : r + 16, c : c + 16] = 2 * block.mean() - 0.05 * (block - block.mean())
    whole = float(depth_correlation(depth, alpha, tiled, patch=0))
    both = float(depth_correlation(depth, alpha, tiled, patch=16))
    assert whole < 0.1 and both > 0.5
    # patch 0 is the whole-view term that patch=16 averages with the tiles'
    covered = (alpha > 0.5).float().flatten()
    expected = 1 - float(pearson(z.flatten(), tiled.flatten(), covered))
    assert whole == pytest.approx(expected, abs=1e-6)


def test_trust_ignores_a_prior_that_contradicts_the_fit_and_follows_one_that_agrees():
    depth, alpha = surface()
    z = depth / alpha
    reversed_ = depth_correlation(depth.clone().requires_grad_(True), alpha, -z, trust=True)
    assert float(reversed_.detach()) == pytest.approx(0.0, abs=1e-4)  # weight max(0, -1) = 0
    noisy = z + 0.3 * torch.randn(z.shape, generator=torch.Generator().manual_seed(0))
    plain = float(depth_correlation(depth, alpha, noisy, patch=0))
    weighted = float(depth_correlation(depth, alpha, noisy, patch=0, trust=True))
    assert weighted == pytest.approx(plain * (1 - plain), rel=1e-5)
    # the weight takes no gradient: the pull is the plain term's, scaled by the weight
    rendered = depth.flip(1).clone().requires_grad_(True)
    depth_correlation(rendered, alpha, noisy, patch=0).backward()
    plain_grad, rendered.grad = rendered.grad.clone(), None
    term = float(depth_correlation(rendered.detach(), alpha, noisy, patch=0))
    depth_correlation(rendered, alpha, noisy, patch=0, trust=True).backward()
    torch.testing.assert_close(rendered.grad, plain_grad * max(0.0, 1 - term))


def test_pool_compares_block_means_so_a_blurred_prior_leaves_the_edges_alone():
    depth, alpha = surface()
    z = depth / alpha
    # a step edge on a block boundary, and the prior's blur of it (a 3-pixel box filter)
    step = torch.where(torch.arange(96) < 48, 1.0, 3.0).expand(64, 96).clone()
    blurred = torch.nn.functional.avg_pool1d(step[:, None, :], 3, 1, 1, count_include_pad=False)
    blurred = blurred[:, 0]
    ones = torch.ones(64, 96)
    pixel = float(depth_correlation(step, ones, blurred, patch=0))
    blocks = float(depth_correlation(step, ones, blurred, patch=0, pool=8))
    assert blocks < 0.2 * pixel
    # a block counts when most of it is covered: the uncovered 8-pixel strip is one block column
    wild = (3 * z + 1).clone()
    wild[:, :8] = torch.rand(64, 8) * 100
    assert float(depth_correlation(depth, alpha, wild, patch=0, pool=8)) < 1e-3
    assert float(depth_correlation(depth, alpha, 3 * z + 1, patch=32, pool=8)) < 1e-5
    # the pull reaches the render's pixels through the block means
    rendered = depth.flip(0).clone().requires_grad_(True)
    depth_correlation(rendered, alpha, z, patch=0, pool=8).backward()
    assert rendered.grad[:, 8:].abs().sum() > 0 and rendered.grad[:, :8].abs().sum() == 0


def test_the_depth_correlation_moves_the_depth_toward_the_prior_and_nothing_covered_is_zero():
    depth, alpha = surface()
    prior = depth / alpha
    wrong = (depth.flip(0)).clone().requires_grad_(True)  # the plane tilted the other way
    loss = depth_correlation(wrong, alpha, prior, patch=16)
    loss.backward()
    assert torch.isfinite(wrong.grad).all() and wrong.grad.abs().sum() > 0
    stepped = (wrong - 50 * wrong.grad).detach()
    assert float(depth_correlation(stepped, alpha, prior, patch=16)) < float(loss.detach())
    empty = torch.zeros(8, 8, requires_grad=True)
    zero = depth_correlation(empty, torch.zeros(8, 8), torch.rand(8, 8))
    zero.backward()
    assert float(zero.detach()) == 0 and empty.grad is not None


def test_the_depth_model_runs_an_image_at_its_size_and_gives_it_back_at_the_images(tmp_path):
    model = MonocularDepth(channel_mean_model(tmp_path / "mean.onnx"))
    assert model.size == (16, 16) and len(model.sha256) == 64
    image = torch.rand(16, 16, 3)
    torch.testing.assert_close(model(image), image.mean(-1), atol=1e-6, rtol=0)
    out = model(torch.rand(24, 40, 3))  # resized to 16 x 16 and back
    assert out.shape == (24, 40) and torch.isfinite(out).all()


def test_a_missing_damaged_or_unfit_depth_model_is_refused_naming_the_option(tmp_path):
    with pytest.raises(DepthPriorError, match=r"fit.depth_model=.*nowhere.onnx.*make weights"):
        MonocularDepth(tmp_path / "nowhere.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(DepthPriorError, match="bad.onnx: not a model onnxruntime can run"):
        MonocularDepth(bad)
    free = channel_mean_model(tmp_path / "free.onnx", size=None)
    with pytest.raises(DepthPriorError, match="free.onnx: it takes .* a fixed size"):
        MonocularDepth(free)


@pytest.fixture(scope="module")
def views():
    s = make_scene(layout="forward", num_gaussians=1500, width=32, height=24, num_train_views=5)
    return s.train_cameras, [rasterize(s.gaussians, c).rgb.clamp(0, 1) for c in s.train_cameras]


def test_the_depth_prior_joins_the_fits_loss_and_the_fit_records_the_model(views, tmp_path):
    cams, imgs = views
    small = dict(iterations=10, init_points=600, densify_from=100, sh_degree=0)
    model = channel_mean_model(tmp_path / "mean.onnx")
    f = SceneFitter(FitConfig(**small, lambda_depth=0.5, depth_model=str(model)), cams, imgs)
    plain = SceneFitter(FitConfig(**small), cams, imgs)
    assert set(f.depth_priors) == set(f.train_idx) and not plain.depth_priors
    view = f.train_idx[0]
    assert f.depth_priors[view].shape == imgs[view].shape[:2]
    loss, _, terms = f.loss(f.gaussians(), view)
    terms = {k: float(v) for k, v in terms.items()}  # the loss keeps them on the device
    assert set(terms) == {"depth"} and 0 < terms["depth"] <= 2
    photometric = plain.loss(plain.gaussians(), view)[0].item()
    assert loss.item() == pytest.approx(photometric + 0.5 * terms["depth"], rel=1e-5)
    metrics = f.fit(progress=False)
    assert np.isfinite(f.history).all() and "depth" in metrics["final_regularisers"]
    assert metrics["depth_model_sha256"] == MonocularDepth(model).sha256
    assert plain.evaluate()["depth_model_sha256"] is None
    with pytest.raises(DepthPriorError, match="fit.depth_model"):
        SceneFitter(FitConfig(**small, lambda_depth=0.5, depth_model="no/such.onnx"), cams, imgs)
    with pytest.raises(ValueError, match="lambda_depth"):
        FitConfig(lambda_depth=-1)


def test_the_depth_settings_reach_the_term(views, tmp_path):
    cams, imgs = views
    small = dict(iterations=10, init_points=600, densify_from=100, sh_degree=0)
    model = str(channel_mean_model(tmp_path / "mean.onnx"))
    settings = dict(depth_patch=0, depth_trust=True, depth_pool=4)
    f = SceneFitter(FitConfig(**small, lambda_depth=0.5, depth_model=model, **settings), cams, imgs)
    view = f.train_idx[0]
    out = render(f.gaussians(), f.cams[view], background=torch.zeros(3), backend=f.cfg.backend)
    expected = depth_correlation(out.depth, out.alpha, f.depth_priors[view], 0, trust=True, pool=4)
    _, _, terms = f.loss(f.gaussians(), view)
    assert terms["depth"] == pytest.approx(float(expected.detach()), rel=1e-4, abs=1e-6)
    for bad in (dict(depth_patch=-1), dict(depth_pool=0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            FitConfig(**bad)


def test_a_camera_between_two_runs_from_one_to_the_other(views):
    cams, _ = views
    a, b = cams[0], cams[3]
    torch.testing.assert_close(between(a, b, 0.0).world_to_cam, a.world_to_cam, atol=1e-5, rtol=0)
    torch.testing.assert_close(between(a, b, 1.0).world_to_cam, b.world_to_cam, atol=1e-5, rtol=0)
    half = between(a, b, 0.5)
    torch.testing.assert_close(half.center, (a.center + b.center) / 2, atol=1e-5, rtol=0)
    R = half.rotation
    torch.testing.assert_close(R @ R.T, torch.eye(3), atol=1e-5, rtol=0)
    angle = lambda x, y: torch.arccos(((x.T @ y).trace() - 1).clamp(-2, 2) / 2)  # noqa: E731
    total = angle(a.rotation, b.rotation)
    assert float(angle(a.rotation, R)) == pytest.approx(float(total) / 2, abs=1e-4)
    assert (half.K == a.K).all() and (half.width, half.height) == (a.width, a.height)


def test_pseudo_views_join_the_loss_on_their_steps_only(views, tmp_path):
    cams, imgs = views
    model = str(channel_mean_model(tmp_path / "mean.onnx"))
    cfg = dict(iterations=8, init_points=600, densify_from=100, sh_degree=0, lambda_depth=0.5)
    f = SceneFitter(
        FitConfig(**cfg, depth_model=model, depth_pseudo_every=3, depth_pseudo_from=2), cams, imgs
    )
    only_photos = SceneFitter(FitConfig(**cfg, depth_model=model), cams, imgs)
    view, g = f.train_idx[0], f.gaussians()
    for step, expected in [(0, False), (1, False), (2, False), (3, True), (6, True), (7, False)]:
        f.step = only_photos.step = step
        loss, _, terms = f.loss(g, view)
        terms = {k: float(v) for k, v in terms.items()}  # the loss keeps them on the device
        assert ("pseudo_depth" in terms) is expected, step
        if expected:
            assert 0 < terms["pseudo_depth"] <= 2
            base = only_photos.loss(only_photos.gaussians(), view)[0].item()
            assert loss.item() == pytest.approx(base + 0.5 * terms["pseudo_depth"], rel=1e-5)
            again = f.loss(g, view)[2]["pseudo_depth"]  # the view is drawn from (seed, step)
            assert again == terms["pseudo_depth"]
    f.step = 0
    assert np.isfinite(f.fit(progress=False)["final_loss"])


FASTDEPTH = ROOT / "weights" / "fastdepth" / "fastdepth.onnx"


@pytest.mark.skipif(not FASTDEPTH.is_file(), reason="FastDepth not fetched (`make weights`)")
def test_fastdepth_puts_a_photographs_table_nearer_than_the_room_behind_it():
    """The real network on a real photograph of a statuette on a table, the room behind."""
    import cv2

    photo = shared_data("mother_child", "images_4", "IMG_0948.JPG")
    image = cv2.resize(cv2.imread(str(photo))[:, :, ::-1], (228, 171), interpolation=cv2.INTER_AREA)
    depth = MonocularDepth(FASTDEPTH)(torch.from_numpy(image.copy()).float() / 255)
    assert depth.shape == (171, 228) and torch.isfinite(depth).all()
    assert float(depth[:40].mean()) > 1.2 * float(depth[-40:].mean())  # the room is farther
