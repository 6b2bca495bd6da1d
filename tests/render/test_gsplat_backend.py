"""gsplat backend: the CPU-testable trace step, and CUDA cross-checks (skipped without CUDA)."""

from __future__ import annotations

import pytest
import torch

from sagonline.render import TraceRequest, project, render
from sagonline.render.gsplat_backend import gsplat_available, trace_step
from sagonline.render.rasterize import rasterize
from tests.fixtures import random_gaussians, small_camera


def _trace_set(chunks):
    return {
        (int(p), int(g)): float(t)
        for c in chunks
        for p, g, t in zip(c.pixel, c.gaussian, c.transmittance, strict=True)
    }


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("n_batches", [1, 3])
def test_trace_step_matches_tiled_trace(kind, n_batches):
    """Feed every candidate (Gaussian, pixel) pair, shuffled, in depth batches."""
    g = random_gaussians(40, kind, seed=11)
    cam = small_camera()
    proj = project(g, cam)
    W, H = cam.width, cam.height
    local = torch.full((len(g),), -1, dtype=torch.long)
    local[proj.ids] = torch.arange(len(proj))
    rank = torch.empty(len(proj), dtype=torch.long)
    rank[torch.sort(proj.depths, stable=True).indices] = torch.arange(len(proj))
    pairs = []
    for li in range(len(proj)):
        x0, x1, y0, y1 = proj.bbox[li].tolist()
        for y in range(max(0, int(y0)), min(H, int(y1) + 1)):
            for x in range(max(0, int(x0)), min(W, int(x1) + 1)):
                pairs.append((int(proj.ids[li]), y * W + x, int(rank[li])))
    pairs = torch.tensor(pairs)
    depth_batch = (pairs[:, 2] * n_batches) // len(proj)
    T = torch.ones(H * W)
    chunks = []
    for b in range(n_batches):
        sel = pairs[depth_batch == b]
        sel = sel[torch.randperm(len(sel), generator=torch.Generator().manual_seed(b))]
        chunk, T = trace_step(
            sel[:, 0],
            sel[:, 1],
            T,
            local,
            rank,
            proj.params(),
            proj.kind,
            W,
            TraceRequest(print, 0.01),
        )
        chunks.append(chunk)
    expected = []
    rasterize(g, cam, trace=TraceRequest(expected.append, eps=0.01))
    got, want = _trace_set(chunks), _trace_set(expected)
    assert set(got) == set(want)
    assert max(abs(got[k] - want[k]) for k in want) < 1e-5


def test_surfels_reach_gsplat_in_its_shapes_and_conventions():
    """gsplat's own PyTorch reference of its 2DGS projection (runs on CPU) must accept what the
    backend passes and produce our ray transforms M = K [R t_u s_u | R t_v s_v | R mu + t]."""
    ref = pytest.importorskip("gsplat.cuda._torch_impl_2dgs")
    from sagonline.render.gsplat_backend import surfel_scales

    g = random_gaussians(50, "2dgs", seed=6)
    cam = small_camera(48, 32)
    ours = project(g, cam)
    _, _, depths, M, _ = ref._fully_fused_projection_2dgs(
        g.means, g.quats, surfel_scales(g.scales), cam.world_to_cam[None], cam.K[None], 48, 32
    )
    torch.testing.assert_close(M[0, ours.ids], ours.transforms, atol=1e-4, rtol=1e-4)
    # gsplat's means2d is the centre of its bounding conic, not the projected centre: not compared
    torch.testing.assert_close(depths[0, ours.ids], ours.depths)


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_an_image_through_gsplat_shades_every_gaussian_without_projecting(monkeypatch, kind):
    """An image-only render hands gsplat every Gaussian's SH colour (the colours the torch path
    gives the splats it draws) and the extra feature channels after them, and runs no projection
    of its own (no wait on the GPU for a cull): simulated on the CPU with gsplat's functions
    keeping what they are given."""
    import sys

    from bench.speed.host_work import StandInGsplat
    from sagonline.render import gsplat_backend

    fake = StandInGsplat()
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)

    def refused(*args, **kwargs):
        raise AssertionError("an image-only render projected the splats")

    monkeypatch.setattr(gsplat_backend, "project", refused)
    g, cam = random_gaussians(60, kind, seed=8, sh_degree=3), small_camera(32, 24)
    features = torch.rand(len(g), 2)
    gsplat_backend.rasterize_gsplat(g, cam, features=features, background=torch.ones(3))
    (given,) = fake.colors
    visible = project(g, cam)
    assert given.shape == (len(g), 5) and len(visible) > 10
    torch.testing.assert_close(given[visible.ids, :3], visible.colors)
    torch.testing.assert_close(given[:, 3:], features)


gpu = pytest.mark.skipif(not gsplat_available(), reason="gsplat backend needs CUDA and gsplat")


@gpu
@pytest.mark.gpu
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_gsplat_image_close_to_torch(kind):
    g = random_gaussians(400, kind, seed=3, spread=1.2).to("cuda")
    cam = small_camera(96, 64).to("cuda")
    ours = render(g, cam, backend="torch")
    theirs = render(g, cam, backend="gsplat")
    assert (ours.rgb - theirs.rgb).abs().mean() < 0.02
    assert (ours.alpha - theirs.alpha).abs().mean() < 0.02


@gpu
@pytest.mark.gpu
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_gsplat_trace_agrees_with_torch(kind):
    g = random_gaussians(400, kind, seed=4, spread=1.2).to("cuda")
    cam = small_camera(96, 64).to("cuda")
    a, b = [], []
    render(g, cam, backend="torch", trace=TraceRequest(a.append, eps=0.01))
    render(g, cam, backend="gsplat", trace=TraceRequest(b.append, eps=0.01))
    sa, sb = set(_trace_set(a)), set(_trace_set(b))
    assert len(sa & sb) / len(sa | sb) > 0.97
