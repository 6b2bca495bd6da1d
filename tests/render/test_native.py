"""The compiled CPU rasterizer: the same images as the PyTorch path, and the same gradients as
autograd through it, for 3DGS and 2DGS."""

from __future__ import annotations

import shutil

import pytest
import torch

from sagonline.render import TraceRequest, render
from sagonline.render.rasterize import rasterize
from sagonline.scene.gaussians import Gaussians
from tests.fixtures import random_gaussians, small_camera

if shutil.which("c++") is None and shutil.which("g++") is None:
    pytest.skip("no C++ compiler: the native rasterizer cannot be built", allow_module_level=True)

from sagonline.render.native import load_extension, rasterize_native  # noqa: E402

LEAVES = ("means", "quats", "scales", "opacities", "sh")


@pytest.fixture(scope="module", autouse=True)
def built():
    load_extension()  # fails the module loudly if the build breaks


def _render_and_grads(fn, g0: Gaussians, cam, features, background):
    leaves = {k: getattr(g0, k).clone().requires_grad_(True) for k in LEAVES}
    out = fn(Gaussians(**leaves), cam, background=background, features=features)
    gen = torch.Generator().manual_seed(3)
    w_rgb = torch.randn(out.rgb.shape, generator=gen)
    w_feat = torch.randn(out.features.shape, generator=gen)
    loss = (
        (out.rgb * w_rgb).sum()
        + 0.3 * out.depth.sum()
        + 0.7 * out.alpha.sum()
        + (out.features * w_feat).sum()
    )
    loss.backward()
    return out, {k: v.grad for k, v in leaves.items()}


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_images_and_gradients_match_the_pytorch_path(kind, seed):
    g = random_gaussians(60, kind, seed=seed)
    cam = small_camera(40, 31)
    feats = torch.rand(60, 2, generator=torch.Generator().manual_seed(seed))
    bg = torch.tensor([0.2, 0.5, 0.1])
    ref, ref_grads = _render_and_grads(rasterize, g, cam, feats, bg)
    nat, nat_grads = _render_and_grads(rasterize_native, g, cam, feats, bg)
    for name in ("rgb", "alpha", "depth", "features"):
        torch.testing.assert_close(getattr(nat, name), getattr(ref, name), atol=2e-6, rtol=1e-5)
    assert (
        float(ref.alpha.detach().max()) > 0.9
    )  # the scene is not empty: there was something to match
    for k in LEAVES:
        scale = float(ref_grads[k].abs().max())
        assert scale > 0, k
        torch.testing.assert_close(nat_grads[k], ref_grads[k], atol=2e-6 * scale, rtol=1e-4)


def test_early_stop_threshold_is_honoured():
    g = random_gaussians(80, "3dgs", seed=4)
    cam = small_camera(32, 24)
    for t_stop in (1e-4, 0.2):
        ref = rasterize(g, cam, t_stop=t_stop)
        nat = rasterize_native(g, cam, t_stop=t_stop)
        torch.testing.assert_close(nat.rgb, ref.rgb, atol=2e-6, rtol=1e-5)


def test_render_routes_traces_to_the_pytorch_path():
    g = random_gaussians(40, "2dgs", seed=2)
    cam = small_camera()
    chunks = []
    request = TraceRequest(chunks.append, eps=0.01, image=True)
    out = render(g, cam, backend="native", return_ids=True, trace=request)
    assert out.ids is not None and chunks  # ids and traces come from the tiled PyTorch path
    plain = render(g, cam, backend="native")
    assert plain.ids is None
    torch.testing.assert_close(plain.rgb, out.rgb, atol=2e-6, rtol=1e-5)


def test_rejects_wrong_packing():
    ext = load_extension()
    with pytest.raises(RuntimeError, match="wrong width"):
        z = torch.zeros
        ext.forward(
            False,
            z(2, 9),
            z(2, 3),
            z(2, 4),
            torch.zeros(0, dtype=torch.long),
            torch.zeros(1, dtype=torch.long),
            torch.zeros(1, dtype=torch.long),
            8,
            8,
            8,
            1e-4,
        )


def test_nothing_in_view_and_trace_requests():
    g = random_gaussians(20, "2dgs", seed=5)
    away = small_camera(eye=(0.0, 40.0, 0.0))  # far away: a few pixels
    behind = small_camera(eye=(0.0, -4.0, 0.0))  # turned round: nothing in view
    behind = type(behind)(
        behind.K, torch.diag(torch.tensor([-1.0, 1, -1, 1])) @ behind.world_to_cam, 26, 19, "b"
    )
    for cam in (away, behind):
        ref, nat = rasterize(g, cam), rasterize_native(g, cam)
        torch.testing.assert_close(nat.rgb, ref.rgb, atol=2e-6, rtol=1e-5)
    empty = rasterize_native(g, behind)
    assert float(empty.alpha.max()) == 0.0 and float(empty.rgb.abs().max()) == 0.0
    assert (rasterize_native(g, behind, return_ids=True).ids == -1).all()


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_counting_sort_bins_like_the_pytorch_sort(kind):
    import math

    from sagonline.render.native import bin_tiles
    from sagonline.render.projection import project
    from sagonline.render.rasterize import bin_tiles as torch_bin_tiles

    g = random_gaussians(500, kind, seed=7, spread=1.2)
    cam = small_camera(61, 45)
    proj = project(g, cam)
    ntx, nty = math.ceil(61 / 8), math.ceil(45 / 8)
    _, order, offsets, counts = torch_bin_tiles(proj, ntx, nty, 8)
    got = bin_tiles(proj, ntx, nty, 8)
    assert order.numel() > 500
    for a, b in zip(got, (order, offsets, counts), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_native_most_visible_ids_and_label_renders_match(kind, seed):
    from sagonline.render import render_labels

    g = random_gaussians(300, kind, seed=seed, spread=0.8)
    cam = small_camera(37, 29)
    ref = rasterize(g, cam, return_ids=True).ids
    got = rasterize_native(g, cam, return_ids=True).ids
    assert (ref >= 0).any() and (ref < 0).any()
    assert torch.equal(got, ref)
    labels = torch.randint(-1, 4, (len(g),), generator=torch.Generator().manual_seed(seed))
    for mode in ("ids", "onehot"):
        a = render_labels(g, cam, labels, 4, mode=mode, backend="torch")
        b = render_labels(g, cam, labels, 4, mode=mode, backend="native")
        assert torch.equal(a, b), mode


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_the_unshaded_surface_is_the_shaded_walks_and_the_label_walks(kind):
    """`surface_native` (the diagnosis's whole view without colours): the alpha, depth and ids of
    the same walk compositing the view's SH colours and of the label render's walk (which hands
    them to the diagnosis), bit for bit, and a full render's to rounding."""
    from sagonline.render.native import (
        label_walk_native,
        prepare_view,
        surface_native,
        walk_prepared,
    )
    from sagonline.render.projection import view_colors

    g = random_gaussians(300, kind, seed=6, spread=0.8)
    cam = small_camera(37, 29)
    alpha, depth, ids = surface_native(g, cam)
    view = prepare_view(g, cam)
    rgb, shaded_depth, shaded_t, shaded_ids = walk_prepared(
        view, cam, view_colors(g, view.ids, cam.center)
    )
    assert rgb.shape == (29, 37, 3) and rgb.abs().sum() > 0
    assert torch.equal(alpha, 1.0 - shaded_t) and torch.equal(depth, shaded_depth)
    assert torch.equal(ids, shaded_ids) and (ids >= 0).any() and (ids < 0).any()
    labels = torch.randint(-1, 3, (len(g),), generator=torch.Generator().manual_seed(2))
    weights, label_ids, label_alpha, label_depth = label_walk_native(g, cam, labels, 3)
    assert weights.shape == (29, 37, 3) and torch.equal(label_ids, ids)
    assert torch.equal(label_alpha, alpha) and torch.equal(label_depth, depth)
    full = rasterize_native(g, cam, return_ids=True)
    torch.testing.assert_close(alpha, full.alpha, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(depth, full.depth, atol=1e-4, rtol=1e-5)
    assert (ids != full.ids).float().mean() < 0.01


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_coverage_draws_each_group_alone_in_one_walk(kind):
    """`render_coverage` on the compiled kernel (one unshaded walk for all the groups) gives
    each group the alpha and depth of its Gaussians' walk alone, bit for bit (and a full
    render's, to rounding): a group, a group inside it, one that overlaps both, an empty one
    and all of them, 8 groups a walk; on torch it is those renders'."""
    from sagonline.render.api import render, render_coverage
    from sagonline.render.native import coverage_native, prepare_view, walk_prepared

    g = random_gaussians(300, kind, seed=4, spread=0.8)
    cam = small_camera(37, 29)
    pick = torch.Generator().manual_seed(1)
    some = torch.rand(len(g), generator=pick) < 0.6
    inside = some & (torch.rand(len(g), generator=pick) < 0.5)
    across = torch.rand(len(g), generator=pick) < 0.3
    groups = torch.stack([some, inside, across, torch.zeros_like(some), torch.ones_like(some)])
    alpha, depth = render_coverage(g, cam, groups, backend="native")
    assert alpha.shape == depth.shape == (5, 29, 37)
    for i, members in enumerate(groups):
        if not members.any():
            assert not alpha[i].any() and not depth[i].any()
            continue
        alone = prepare_view(g.subset(members), cam)  # the group's own walk, no colours
        _, own_depth, own_t, _ = walk_prepared(alone, cam, torch.zeros(len(alone.ids), 0))
        assert torch.equal(alpha[i], 1.0 - own_t) and torch.equal(depth[i], own_depth), i
        full = rasterize_native(g.subset(members), cam)  # projected with autograd: close
        assert (full.alpha > 0.5).any() and (full.alpha < 0.01).any()
        torch.testing.assert_close(alpha[i], full.alpha, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(depth[i], full.depth, atol=1e-4, rtol=1e-5)
    torch_alpha, torch_depth = render_coverage(g, cam, groups[:2], backend="torch")
    for i, members in enumerate(groups[:2]):
        ref = render(g.subset(members), cam, backend="torch")
        assert torch.equal(torch_alpha[i], ref.alpha) and torch.equal(torch_depth[i], ref.depth)
    with pytest.raises(ValueError, match="groups must be"):  # a bit a group: 8 at most
        coverage_native(g, cam, torch.ones(9, len(g), dtype=torch.bool))
    nine = render_coverage(g, cam, groups[[0] * 9], backend="native")[0]  # in two walks
    assert nine.shape == (9, 29, 37) and torch.equal(nine[8], alpha[0])
    nothing = render_coverage(g, cam, groups[3:4], backend="native")  # no Gaussian at all
    assert not nothing[0].any() and not nothing[1].any()
