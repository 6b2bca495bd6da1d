"""The Triton walks' tile lists made by `triton_prepare`'s two kernels (Triton's interpreter on
the CPU) against PyTorch's: the same splats, parameters, boxes and lists, and so the same votes
and renders, on scenes with every kind of Gaussian the projection culls."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from sagonline.render import vote_histogram
from sagonline.scene.gaussians import Gaussians
from tests.fixtures import random_gaussians, small_camera
from tests.render.test_vote_op import RULES, _check_image_walk, _masks, _same

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("triton") is None,
    reason="triton is not installed (pip install -e '.[triton]')",
)
EYES = [(0.3, -4.0, 0.8), (3.5, -1.0, 1.5), (-2.0, 3.0, -1.0)]


def _hostile(kind: str, n: int = 240) -> Gaussians:
    """Random Gaussians, then: copies of some (equal depths: ties keep projection order), some
    too faint to reach 1/255, some off screen in every view of EYES, some behind its first
    or in front of it nearer than the near plane, some large
    enough to cover more tiles than an emission step takes, some with an opacity just above
    1/255 (the reach box shrinks to nearly nothing) and, for surfels, some seen edge-on."""
    g = random_gaussians(n, kind, seed=7, spread=0.8)
    means, scales = g.means.clone(), g.scales.clone()
    opac, quats = g.opacities.clone(), g.quats.clone()
    opac[10:20] = 1e-3  # never 1/255
    opac[20:30] = 1.0 / 255.0 + 1e-4
    means[30:40] = torch.tensor([0.0, 0.0, 60.0])  # far beyond any view's sides
    means[40:45] = torch.tensor([0.45, -6.0, 1.2])  # behind the camera at EYES[0]
    eye = torch.tensor(EYES[0])
    means[45:50] = eye - 0.005 * eye / eye.norm()  # in front of it, nearer than `near`
    scales[50:56] = 2.5  # a quarter of the view and more
    if kind == "2dgs":  # normals along the view direction of EYES[0]: seen edge-on
        quats[56:66] = torch.tensor([0.7071, 0.7071, 0.0, 0.0])
    g = Gaussians(means=means, quats=quats, scales=scales, opacities=opac, sh=g.sh)
    return g.subset(torch.cat([torch.arange(n), torch.arange(60, 80)]))  # 20 exact copies


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_the_fused_tile_lists_are_pytorchs(kind):
    from sagonline.render.triton_prepare import tile_view_fused
    from sagonline.render.triton_vote import tile_view

    g = _hostile(kind)
    for view, eye in enumerate(EYES):
        cam = small_camera(96, 72, eye=eye)
        ref = tile_view(g, cam, 0.01, with_colors=True)
        got = tile_view_fused(g, cam, 0.01, with_colors=True)
        kept = set(ref.proj.ids.tolist())
        assert not kept & set(range(10, 20)) and not kept & set(range(30, 40))  # faint, off
        assert view > 0 or not kept & set(range(40, 50))  # behind, too near
        assert torch.equal(got.proj.ids, ref.proj.ids)
        torch.testing.assert_close(got.params, ref.params, rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(got.proj.bbox, ref.proj.bbox, rtol=1e-5, atol=1e-3)
        torch.testing.assert_close(got.proj.colors, ref.proj.colors)
        assert torch.equal(got.counts, ref.counts)
        assert torch.equal(got.offsets, ref.offsets)
        assert torch.equal(got.order, ref.order)
        assert int(ref.counts.max()) > 16  # a tile lists more splats than ...
        assert int(ref.counts.sum()) > 5 * len(ref.proj)  # ... and splats cover several tiles


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("rule", ["rgc", "rgc-eps.2-delta.7", "blend"])
def test_the_vote_on_fused_tile_lists_is_the_references(kind, rule, monkeypatch):
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "fused")
    g = _hostile(kind)
    cam = small_camera(40, 30, eye=EYES[1])
    labels = _masks(cam, 3, 1)
    ref = vote_histogram(g, cam, labels, 3, RULES[rule], backend="torch")
    got = vote_histogram(g, cam, labels, 3, RULES[rule], backend="triton")
    _same(got, ref, RULES[rule].weighting)


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_the_image_walk_on_fused_tile_lists_matches_the_rasterizer(kind, monkeypatch):
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "fused")
    _check_image_walk(random_gaussians(40, kind, seed=4, spread=0.6), small_camera(20, 15))


def test_the_camera_row_is_made_where_the_camera_is_without_a_read(monkeypatch):
    """`_camera_row` (the projection kernel's camera constants) reads no value on the host (on
    a GPU each read waited for it, twice a vote) and gives the frustum's limits by hand."""
    from torch.profiler import ProfilerActivity, profile

    from sagonline.render.triton_prepare import _camera_row

    cam = small_camera(960, 540)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        row = _camera_row(cam)
    names = {e.name for e in prof.events()}
    assert not names & {"aten::_local_scalar_dense", "aten::item"}
    K = cam.K.double()
    fx, cx = float(K[0, 0]), float(K[0, 2])
    assert row.shape == (25,) and row.dtype == torch.float32
    assert float(row[21]) == pytest.approx(cx / fx + 0.3 * 960 / (2 * fx))
    assert torch.equal(row[12:21], cam.K.flatten())


def test_nothing_on_screen_is_no_view_and_no_votes(monkeypatch):
    from sagonline.render.triton_prepare import tile_view_fused

    g = random_gaussians(50, "3dgs", seed=1, spread=0.5)
    behind = Gaussians(
        g.means + torch.tensor([0.0, -9.0, 0.0]), g.quats, g.scales, g.opacities, g.sh
    )
    cam = small_camera(20, 15)
    assert tile_view_fused(behind, cam, 0.01, with_colors=False) is None
    empty = g.subset(torch.zeros(0, dtype=torch.long))
    assert tile_view_fused(empty, cam, 0.01, with_colors=False) is None
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "fused")
    hist = vote_histogram(behind, cam, _masks(cam, 2, 0), 2, RULES["rgc"], backend="triton")
    assert float(hist.abs().sum()) == 0.0


def test_an_unknown_preparation_is_refused_and_each_keys_its_own_cache(monkeypatch):
    from sagonline.render.backends import implementation_digest
    from sagonline.render.triton_prepare import chosen_tile_view, tile_view_fused
    from sagonline.render.triton_vote import tile_view

    digests = set()
    for name in ("torch", "fused"):
        monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", name)
        digests.add(implementation_digest("triton"))
    assert len(digests) == 2
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "torch")
    want = {False: implementation_digest("triton")}
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "fused")
    want[True] = implementation_digest("triton")
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "")
    for cuda in (False, True):  # unset: the fused lists where CUDA is, PyTorch's elsewhere
        monkeypatch.setattr(torch.cuda, "is_available", lambda cuda=cuda: cuda)
        assert implementation_digest("triton") == want[cuda]
        assert chosen_tile_view() is (tile_view_fused if cuda else tile_view)
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "cuda")
    g = random_gaussians(20, "3dgs", seed=1, spread=0.5)
    cam = small_camera(20, 15)
    with pytest.raises(ValueError, match=r"SAGONLINE_TRITON_PREPARE='cuda'.*fused"):
        vote_histogram(g, cam, _masks(cam, 2, 0), 2, RULES["rgc"], backend="triton")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_the_fused_tile_lists_on_cuda(kind, monkeypatch):
    """Compiled: the tile lists are PyTorch's on the same GPU (the sort and bincount included,
    up to a last bit's rounding) and the votes and images on them the reference's, on the GPU
    test's inputs."""
    from sagonline.render.triton_prepare import tile_view_fused
    from sagonline.render.triton_vote import tile_view
    from tests.render.test_vote_op import KERNEL_CASES, _check_kernel_case

    g = _hostile(kind).to("cuda")
    for eye in EYES:
        cam = small_camera(320, 240, eye=eye).to("cuda")
        ref, got = tile_view(g, cam, 0.01, True), tile_view_fused(g, cam, 0.01, True)
        assert torch.equal(got.proj.ids, ref.proj.ids)
        torch.testing.assert_close(got.params, ref.params, rtol=1e-5, atol=1e-4)
        # a fused multiply-add may move a box edge or a depth by its last bit: a near-tie of
        # two depths, or an edge on a tile's border, may list a pair otherwise; a few at most
        assert int((got.counts != ref.counts).sum()) <= 2
        if torch.equal(got.counts, ref.counts):
            assert float((got.order != ref.order).float().mean()) < 1e-3
    monkeypatch.setenv("SAGONLINE_TRITON_PREPARE", "fused")
    for case in KERNEL_CASES:
        if case.startswith(kind):
            _check_kernel_case(case, "cuda", views=3)
    _check_image_walk(random_gaussians(3000, kind, seed=0, spread=0.8).to("cuda"), cam)
