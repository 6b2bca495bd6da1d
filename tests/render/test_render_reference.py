"""The tiled fast path against the brute-force per-pixel reference, images and traces."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.render import RasterStats, TraceRequest
from sagonline.render.rasterize import rasterize
from sagonline.render.reference import reference_render
from tests.fixtures import random_gaussians, small_camera


def _fast_trace(g, cam, eps):
    rows = []
    rasterize(g, cam, trace=TraceRequest(rows.append, eps=eps))
    if not rows:
        return {}
    cat = {
        k: torch.cat([getattr(c, k) for c in rows])
        for k in ("pixel", "gaussian", "transmittance", "alpha", "distance")
    }
    return {
        (int(p), int(g_)): (float(t), float(a), float(d))
        for p, g_, t, a, d in zip(
            *(cat[k] for k in ("pixel", "gaussian", "transmittance", "alpha", "distance")),
            strict=True,
        )
    }


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("tile_size,block", [(8, 64), (16, 4)])
def test_image_matches_reference(kind, seed, tile_size, block):
    g = random_gaussians(40, kind, seed=seed)
    cam = small_camera(eye=(0.5 * seed, -4.0, 0.6))
    feats = torch.nn.functional.one_hot(torch.arange(40) % 3, 3).float()
    fast = rasterize(
        g,
        cam,
        features=feats,
        return_ids=True,
        tile_size=tile_size,
        block=block,
        background=torch.tensor([0.1, 0.2, 0.3]),
    )
    ref = reference_render(g, cam, features=feats, background=(0.1, 0.2, 0.3))
    assert ref.alpha.max() > 0.5, "the scene must cover the view for the test to mean anything"
    np.testing.assert_allclose(fast.rgb.numpy(), ref.rgb, atol=2e-4)
    np.testing.assert_allclose(fast.alpha.numpy(), ref.alpha, atol=2e-5)
    np.testing.assert_allclose(fast.depth.numpy(), ref.depth, atol=5e-4)
    np.testing.assert_allclose(fast.features.numpy(), ref.features, atol=2e-5)
    assert (fast.ids.numpy() == ref.ids).mean() > 0.99


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("seed", [3, 4])
@pytest.mark.parametrize("eps", [0.01, 0.3])
def test_trace_matches_reference(kind, seed, eps):
    g = random_gaussians(40, kind, seed=seed)
    cam = small_camera()
    ref = reference_render(g, cam, trace_eps=eps)
    expected = {(p, i): (t, a, d) for p, i, t, a, d in ref.trace}
    got = _fast_trace(g, cam, eps)
    assert len(expected) > 200
    assert set(got) == set(expected)
    for key, (t, a, d) in expected.items():
        gt, ga, gd = got[key]
        assert gt == pytest.approx(t, abs=1e-5)
        assert ga == pytest.approx(a, abs=2e-5)
        assert gd == pytest.approx(d, abs=1e-4)


def test_trace_is_streamed_in_chunks():
    g = random_gaussians(200, "3dgs", seed=5, spread=1.5)
    cam = small_camera(64, 48)
    sizes = []
    request = TraceRequest(lambda c: sizes.append(len(c)), eps=0.01)
    rasterize(g, cam, trace=request, max_elements=1 << 13)
    assert len(sizes) > 3
    assert max(sizes) < sum(sizes)


def test_trace_distance_filter_and_stats():
    g = random_gaussians(40, "3dgs", seed=6)
    cam = small_camera()
    full = _fast_trace(g, cam, 0.01)
    near = []
    stats = RasterStats()
    rasterize(g, cam, trace=TraceRequest(near.append, 0.01, delta=2.0), stats=stats)
    kept = {(int(p), int(i)) for c in near for p, i in zip(c.pixel, c.gaussian, strict=True)}
    assert kept == {k for k, v in full.items() if v[2] < 2.0}
    assert stats.intersections > 0 and stats.evaluations >= stats.intersections


def test_empty_view_is_background():
    g = random_gaussians(10, "3dgs", seed=7)
    cam = small_camera(eye=(0, 4.0, 0))
    behind = g.subset(torch.zeros(10, dtype=torch.bool))
    out = rasterize(behind, cam, background=torch.tensor([1.0, 0.5, 0.0]))
    assert torch.allclose(out.rgb, torch.tensor([1.0, 0.5, 0.0]).expand_as(out.rgb))
    assert out.alpha.abs().max() == 0


def test_misspelt_render_option_is_refused():
    from sagonline.render import render

    g = random_gaussians(10, "3dgs", seed=0)
    with pytest.raises(TypeError, match="trace_tmin"):
        render(g, small_camera(), trace_tmin=0.5)
