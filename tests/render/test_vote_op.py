"""The vote op, `vote_histogram`: every implementation against the PyTorch reference on tiny
3DGS and 2DGS scenes (occlusion, the eps stop, the delta rule, several labels), and the
label renders' walks against the rasterizer."""

from __future__ import annotations

import importlib.util
import shutil
from dataclasses import replace
from functools import partial

import pytest
import torch

from sagonline.render import vote_histogram
from sagonline.render.rasterize import rasterize
from sagonline.render.rule import VoteRule
from sagonline.scene.gaussians import Gaussians
from tests.fixtures import random_gaussians, small_camera
from tests.render.blend_bound import blend_bound

HAS_COMPILER = shutil.which("c++") is not None or shutil.which("g++") is not None
HAS_TRITON = importlib.util.find_spec("triton") is not None
needs_compiler = pytest.mark.skipif(not HAS_COMPILER, reason="no C++ compiler for the kernel")
needs_triton = pytest.mark.skipif(
    not HAS_TRITON, reason="triton is not installed (pip install -e '.[triton]')"
)
RULES = {
    "rgc": VoteRule(eps=0.01, delta=2.0, weighting="count"),
    "rgc-eps.2-delta.7": VoteRule(eps=0.2, delta=0.7, weighting="count"),
    "rgc-eps0-delta6": VoteRule(eps=0.0, delta=6.0, weighting="count"),
    "blend": VoteRule(eps=1e-4, delta=None, weighting="blend"),
}


def _masks(cam, k: int, seed: int) -> torch.Tensor:
    return torch.randint(
        0, k, (cam.height, cam.width), generator=torch.Generator().manual_seed(seed)
    )


def _same(got: torch.Tensor, ref: torch.Tensor, weighting: str, bound_of=None) -> None:
    """Counts exactly; blend weights within `blend_bound` (float32 drift and decision flips,
    derived in tests/render/blend_bound.py), or to float32 rounding without `bound_of`."""
    assert ref.sum() > 0  # there was something to match
    if weighting == "count":
        assert torch.equal(got, ref)
    elif bound_of is None:
        torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-7)
    else:
        exact, bound = bound_of()
        off = (got - exact).abs() > bound
        assert not off.any(), (
            f"{int(off.sum())} of {off.numel()} weights outside the bound; worst "
            f"{float(((got - exact).abs() - bound).max()):.3g}"
        )


def _scene_views(kind: str, seed: int, n: int, width: int, height: int):
    g = random_gaussians(n, kind, seed=seed, spread=0.8)
    eyes = [(0.3, -4.0, 0.8), (3.5, -1.0, 1.5), (-2.0, 3.0, -1.0)]
    return g, [small_camera(width, height, eye=e, name=f"c{i}") for i, e in enumerate(eyes)]


@needs_compiler
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("rule", list(RULES))
def test_native_matches_the_reference(kind, seed, rule):
    """Counts exactly; blend weights within the derived bound: torch's own exp and products
    round by the machine's vector width (on AVX-512, 2 of 1,200 weights were 3.7e-5 apart,
    past a plain float32 tolerance), the kernel's do not."""
    g, cams = _scene_views(kind, seed, 300, 37, 29)
    for i, cam in enumerate(cams):
        k = 3 + i  # 3, 4 and 5 labels
        labels = _masks(cam, k, seed + i)
        ref = vote_histogram(g, cam, labels, k, RULES[rule], backend="torch")
        got = vote_histogram(g, cam, labels, k, RULES[rule], backend="native")
        blend = RULES[rule].weighting == "blend"
        bound = partial(blend_bound, g, cam, labels, k, RULES[rule]) if blend else None
        _same(got, ref, RULES[rule].weighting, bound)


TRITON_VOTE_KERNELS = ["walk", "chunk16", "chunk32", "chunk16w16"]


@needs_triton
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("rule", ["rgc", "rgc-eps.2-delta.7", "rgc-eps0-delta6", "blend"])
@pytest.mark.parametrize("kernel", TRITON_VOTE_KERNELS)
def test_triton_kernel_matches_the_reference(kind, rule, kernel, monkeypatch):
    """The fused GPU kernels (the splat walk and the chunked vote), run by Triton's interpreter
    on the CPU (on CUDA with -m gpu)."""
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", kernel)
    g, cams = _scene_views(kind, 3, 40, 20, 15)
    labels = _masks(cams[0], 3, 0)
    ref = vote_histogram(g, cams[0], labels, 3, RULES[rule], backend="torch")
    got = vote_histogram(g, cams[0], labels, 3, RULES[rule], backend="triton")
    _same(got, ref, RULES[rule].weighting)


def _walls(*walls: tuple[float, float]) -> Gaussians:
    """Flat opaque 3DGS discs (depth, size) facing the camera, which looks along +y."""
    n = len(walls)
    return Gaussians(
        means=torch.tensor([[0.0, depth, 0.0] for depth, _ in walls]),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        scales=torch.tensor([[size, 0.01, size] for _, size in walls]),
        opacities=torch.ones(n),
        sh=torch.zeros(n, 4, 3),
    )


BACKENDS = ["torch"] + (["native"] if HAS_COMPILER else []) + (["triton"] if HAS_TRITON else [])


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_front_surface_hides_the_back_one_until_eps(backend):
    """A wide opaque front wall (alpha clipped to 0.99 at every pixel) leaves T = 0.01 behind
    it: with eps = 0.01 the back wall gets no vote, with eps = 0.001 it does; the front wall's
    votes do not depend on eps."""
    g = _walls((-1.0, 50.0), (1.0, 2.0))
    cam = small_camera(16, 12, eye=(0.0, -4.0, 0.0))
    labels = torch.ones(12, 16, dtype=torch.long)
    strict = vote_histogram(g, cam, labels, 2, VoteRule(eps=0.01, delta=None), backend=backend)
    loose = vote_histogram(g, cam, labels, 2, VoteRule(eps=0.001, delta=None), backend=backend)
    assert strict[0, 1] > 0 and strict[1].sum() == 0
    assert loose[1, 1] > 0 and loose[0, 1] == strict[0, 1]


@pytest.mark.parametrize("backend", BACKENDS)
def test_delta_keeps_only_gaussians_centred_near_the_pixel(backend):
    g = random_gaussians(40, "3dgs", seed=5, spread=0.6)
    cam = small_camera(20, 15)
    labels = _masks(cam, 2, 1)
    total = [
        float(vote_histogram(g, cam, labels, 2, VoteRule(delta=d), backend=backend).sum())
        for d in (1e-6, 0.5, 2.0, 6.0)
    ]
    assert total[0] == 0 and 0 < total[1] < total[2] < total[3]


@needs_compiler
def test_avx2_and_baseline_walks_agree_bit_for_bit(monkeypatch):
    from sagonline.render.native import vote_simd

    g, cams = _scene_views("2dgs", 4, 300, 37, 29)
    labels = _masks(cams[0], 3, 0)
    fast = vote_histogram(g, cams[0], labels, 3, RULES["blend"], backend="native")
    simd = vote_simd()
    monkeypatch.setenv("SAGONLINE_VOTE_SIMD", "generic")
    assert vote_simd() == "generic"
    plain = vote_histogram(g, cams[0], labels, 3, RULES["blend"], backend="native")
    assert torch.equal(fast, plain), simd


@needs_compiler
def test_native_vote_does_not_depend_on_the_thread_count():
    g, cams = _scene_views("3dgs", 6, 400, 40, 30)
    labels = _masks(cams[0], 2, 0)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = vote_histogram(g, cams[0], labels, 2, RULES["blend"], backend="native")
        torch.set_num_threads(2)
        two = vote_histogram(g, cams[0], labels, 2, RULES["blend"], backend="native")
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)  # merged in tile order


@needs_compiler
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_compiled_projection_matches_project(kind):
    from sagonline.render.native import prepare_view
    from sagonline.render.projection import project

    g = random_gaussians(300, kind, seed=8, spread=5.0)  # some behind the camera or off screen
    cam = small_camera(37, 29)
    proj, view = project(g, cam, with_colors=False), prepare_view(g, cam)
    # its boxes bound alpha >= 1/255, inside the 3-sigma boxes: a splat whose faint rim alone
    # reaches the screen may be culled as well
    common = torch.isin(proj.ids, view.ids)
    assert torch.equal(proj.ids[common], view.ids) and 0.9 * len(proj) <= len(view.ids) < 300
    torch.testing.assert_close(view.params, proj.params()[common], rtol=1e-4, atol=1e-4)
    assert (view.boxes[:, 0] >= proj.bbox[common, 0] - 1e-3).all()
    assert (view.boxes[:, 1] <= proj.bbox[common, 1] + 1e-3).all()


def test_the_op_rejects_bad_inputs():
    g = random_gaussians(10, "3dgs")
    cam = small_camera(8, 6)
    with pytest.raises(ValueError, match="6x8"):
        vote_histogram(g, cam, torch.zeros(5, 8, dtype=torch.long), 2, VoteRule())
    with pytest.raises(ValueError, match=r"\[0, 2\)"):
        vote_histogram(g, cam, torch.full((6, 8), 2), 2, VoteRule())
    with pytest.raises(ValueError, match="float64"):
        vote_histogram(
            g, cam, torch.zeros(6, 8, dtype=torch.long), 2, VoteRule(), out=torch.zeros(10, 2)
        )
    with pytest.raises(ValueError, match="weighting"):
        VoteRule(weighting="mean")


def test_labels_given_on_the_host_are_checked_there():
    """A mask comes from the segmenter on the host: its ids are checked there, before it goes to
    the Gaussians' device (on a GPU the check there waited for it). Gaussians on PyTorch's
    `meta` device, which holds no values, show where: a check there could not read them."""
    from sagonline.render.vote import vote_into

    g = random_gaussians(10, "3dgs").to("meta")
    cam = small_camera(8, 6)
    hist = torch.zeros(10, 2, dtype=torch.float64, device="meta")
    with pytest.raises(ValueError, match=r"\[0, 2\)"):
        vote_into(g, cam, torch.full((6, 8), 2), VoteRule(), hist)


def test_a_mask_crosses_to_the_gaussians_device_in_the_narrowest_type(monkeypatch):
    """To another device a mask crosses as bytes for up to 256 labels (int32 past them) and is
    widened there; on the Gaussians' own device it is the tensor given. `meta` stands for the
    GPU here (the CUDA tests vote host masks on CUDA: tests/render/test_vote_op.py, -m gpu)."""
    from sagonline.render.vote import label_type, on_device

    assert label_type(2) == label_type(256) == torch.uint8 and label_type(257) == torch.int32
    labels = torch.randint(0, 3, (6, 8))
    assert on_device(labels, torch.device("cpu"), 3) is labels
    crossed = []
    to = torch.Tensor.to
    monkeypatch.setattr(
        torch.Tensor, "to", lambda t, *a, **k: crossed.append(t.dtype) or to(t, *a, **k)
    )
    there = on_device(labels, torch.device("meta"), 3)
    assert there.device.type == "meta" and there.dtype == torch.long and there.shape == (6, 8)
    assert crossed == [torch.int64, torch.uint8]  # narrowed on the host, then moved as bytes


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != "torch"])
def test_label_walks_match_the_rasterizer(kind, backend):
    """One-hot label weights (unlabelled Gaussians occlude but add nothing) and the most
    visible Gaussian, from the compiled and the Triton walk, against `rasterize`."""
    from sagonline.render.api import _label_walk

    g = random_gaussians(40, kind, seed=2, spread=0.6)
    cam = small_camera(20, 15)
    splat_labels = torch.randint(-1, 3, (40,), generator=torch.Generator().manual_seed(1))
    onehot = torch.nn.functional.one_hot(splat_labels.clamp_min(0), 3).float()
    onehot *= (splat_labels >= 0)[:, None].float()
    ref = rasterize(g, cam, features=onehot, return_ids=True)
    weights, ids, _ = _label_walk(g, cam, splat_labels, 3, "onehot", backend)
    torch.testing.assert_close(weights, ref.features, rtol=1e-5, atol=1e-6)
    assert float(ref.features.max()) > 0.5
    assert torch.equal(ids, ref.ids)


def _check_image_walk(g, cam) -> None:
    """The Triton composite as an image renderer against `rasterize`: colour over a
    background, alpha, weighted depth, features beside colour, the most visible Gaussian."""
    from sagonline.render.triton_composite import rasterize_triton

    features = torch.rand(len(g), 2, generator=torch.Generator().manual_seed(3)).to(g.device)
    background = torch.tensor([0.2, 0.5, 0.9], device=g.device)
    ref = rasterize(g, cam, background=background, features=features, return_ids=True)
    got = rasterize_triton(g, cam, background=background, features=features, return_ids=True)
    assert float(ref.alpha.max()) > 0.5  # there was something to match
    for name in ("rgb", "alpha", "depth", "features"):
        a, b = getattr(got, name), getattr(ref, name)
        off = ~torch.isclose(a, b, rtol=1e-4, atol=2e-5)
        # A compiled walk rounds differently (fused multiply-adds, another exp): a pixel where
        # a splat sits at a threshold (the 3-sigma cutoff, alpha >= 1/255, the t_stop end) may
        # take or drop it, which moves that pixel by at most the splat's alpha there: <= 0.99
        # exp(-4.5) = 0.011 of its colour (the H100 moved 2 of 230,400 values by 1.2e-4). So a
        # few values may be off, and only by that much; a wrong walk moves most of them.
        assert off.float().mean() < 1e-3, f"{name}: {int(off.sum())} of {off.numel()} off"
        scale = 1.0 if name != "depth" else float(b.abs().max())
        assert float((a - b).abs().max()) <= 0.02 * scale, name
    assert (got.ids != ref.ids).float().mean() < 1e-3  # ties of equal weight may differ


@needs_triton
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_triton_image_walk_matches_the_rasterizer(kind):
    _check_image_walk(random_gaussians(40, kind, seed=4, spread=0.6), small_camera(20, 15))


@needs_triton
def test_a_render_that_needs_gradients_never_takes_the_triton_walk():
    from sagonline.render import render

    g = random_gaussians(30, "3dgs", seed=5, spread=0.6)
    cam = small_camera(12, 9)
    g.opacities.requires_grad_(True)
    out = render(g, cam, backend="triton")
    out.rgb.sum().backward()  # the PyTorch twin rendered it: there is a backward pass
    assert g.opacities.grad is not None and g.opacities.grad.abs().sum() > 0
    with torch.no_grad():
        walked = render(g, cam, backend="triton")
    assert walked.rgb.grad_fn is None
    torch.testing.assert_close(walked.rgb, out.rgb.detach(), rtol=1e-4, atol=2e-5)


# The inputs the fused kernel is checked on: on CUDA (-m gpu) all of them, in Triton's
# interpreter on the CPU the small ones (an interpreted walk takes ~20 s a view there).
KERNEL_CASES = {
    "3dgs-800-96x72": ("3dgs", 800, 96, 72),
    "2dgs-800-96x72": ("2dgs", 800, 96, 72),
    "3dgs-3000-320x240": ("3dgs", 3000, 320, 240),
    "2dgs-3000-320x240": ("2dgs", 3000, 320, 240),
}
# The interpreter takes about 30 s per rule and case for the splat walk: each kind with one of
# the rules (both rules on both kinds run at the small size in
# test_triton_kernel_matches_the_reference). The chunked vote takes under a second at 96x72 and
# 15-20 s a rule at 320x240 there (2 cores, the suite beside it): both rules at the small size,
# one a kind at 320x240, each rule on one kind (on CUDA, -m gpu runs every case and rule).
INTERPRETED = {"3dgs-800-96x72": ("rgc",), "2dgs-800-96x72": ("blend",)}
INTERPRETED_CHUNKS = {
    "3dgs-800-96x72": ("rgc", "blend"),
    "2dgs-800-96x72": ("rgc", "blend"),
    "3dgs-3000-320x240": ("blend",),
    "2dgs-3000-320x240": ("rgc",),
}


def _check_kernel_case(case: str, device: str, views: int, rules=("rgc", "blend")) -> None:
    kind, n, width, height = KERNEL_CASES[case]
    g, cams = _scene_views(kind, 0, n, width, height)
    g = g.to(device)
    for cam in cams[:views]:
        cam = replace(cam).to(device)
        labels = _masks(cam, 4, 0).to(device)
        for rule in rules:
            ref = vote_histogram(g, cam, labels, 4, RULES[rule], backend="torch")
            got = vote_histogram(g, cam, labels, 4, RULES[rule], backend="triton")
            bound = partial(blend_bound, g, cam, labels, 4, RULES["blend"])
            _same(got, ref, RULES[rule].weighting, bound)


@pytest.mark.slow
@needs_triton
@pytest.mark.parametrize("case", INTERPRETED)
def test_triton_kernel_on_the_gpu_tests_inputs_in_the_interpreter(case):
    if torch.cuda.is_available():
        pytest.skip("CUDA is here: the gpu test runs these inputs compiled")
    _check_kernel_case(case, "cpu", views=1, rules=INTERPRETED[case])


@pytest.mark.slow
@needs_triton
@pytest.mark.parametrize("case", INTERPRETED_CHUNKS)
def test_the_chunked_vote_on_the_gpu_tests_inputs_in_the_interpreter(case, monkeypatch):
    """Counts exact, blend weights within the derived bound, as the splat walk's."""
    if torch.cuda.is_available():
        pytest.skip("CUDA is here: the gpu test runs these inputs compiled")
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", "chunk16")
    _check_kernel_case(case, "cpu", views=1, rules=INTERPRETED_CHUNKS[case])


@needs_triton
def test_the_chunked_count_over_many_labels_is_the_references(monkeypatch):
    """The default count kernel on CUDA with more labels than tl.dot's smallest side (40:
    padded to 64 columns), in the interpreter: the reference's counts exactly."""
    if torch.cuda.is_available():
        pytest.skip("CUDA is here: the gpu tests run the kernels compiled")
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", "chunk16")
    g, cams = _scene_views("2dgs", 0, 800, 48, 36)
    labels = _masks(cams[0], 40, 1)
    ref = vote_histogram(g, cams[0], labels, 40, RULES["rgc"], backend="torch")
    got = vote_histogram(g, cams[0], labels, 40, RULES["rgc"], backend="triton")
    assert (ref[:, 16:] > 0).any()  # labels past the first 16 voted
    _same(got, ref, "count")


@needs_triton
def test_an_unknown_triton_vote_kernel_is_refused_and_each_kernel_keys_its_own_cache(
    monkeypatch,
):
    from sagonline.render.backends import implementation_digest

    g, cams = _scene_views("3dgs", 3, 40, 20, 15)
    digests = set()
    for kernel in TRITON_VOTE_KERNELS:
        monkeypatch.setenv("SAGONLINE_TRITON_VOTE", kernel)
        digests.add(implementation_digest("triton"))
    assert len(digests) == len(TRITON_VOTE_KERNELS)  # a vote cached by one is not another's
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", "")
    assert implementation_digest("triton") not in digests  # unset: by the rule, keyed apart
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", "chunk8")
    with pytest.raises(ValueError, match=r"SAGONLINE_TRITON_VOTE='chunk8'.*walk"):
        vote_histogram(g, cams[0], _masks(cams[0], 3, 0), 3, RULES["rgc"], backend="triton")


def test_unset_the_vote_kernel_follows_the_rule_on_cuda_and_walks_on_the_cpu(monkeypatch):
    """Where CUDA is, counts take the chunked vote (faster on both bench scenes in two GPU
    runs, the same votes) up to the labels its shared memory holds, and blends the walk (the
    chunked blend spills registers, untimed); on the CPU the walk; SAGONLINE_TRITON_VOTE
    overrides both."""
    import torch

    from sagonline.render import backends

    monkeypatch.delenv("SAGONLINE_TRITON_VOTE", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert backends.triton_vote_kernel("count") == "chunk16"
    assert backends.triton_vote_kernel("count", backends.CHUNKED_MAX_LABELS) == "chunk16"
    assert backends.triton_vote_kernel("count", backends.CHUNKED_MAX_LABELS + 1) == "walk"
    assert backends.triton_vote_kernel("blend") == "walk"
    assert backends.triton_vote_kernel() == "auto"
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", "chunk32")
    assert backends.triton_vote_kernel("count") == backends.triton_vote_kernel("blend") == "chunk32"
    with pytest.raises(ValueError, match="chunk32: a chunked vote holds at most 256 labels.*257"):
        backends.triton_vote_kernel("count", backends.CHUNKED_MAX_LABELS + 1)
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", "walk")
    assert backends.triton_vote_kernel("count", 1000) == "walk"
    monkeypatch.delenv("SAGONLINE_TRITON_VOTE")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert backends.triton_vote_kernel("count") == backends.triton_vote_kernel("blend") == "walk"


def test_the_vote_op_launches_the_kernel_its_rule_chooses(monkeypatch):
    """`render.vote.implementation` hands the rule's weighting to the choice: a count launches
    the chunked vote where it is chosen, a blend the walk."""
    from sagonline.render import backends
    from sagonline.render import vote as vote_op
    from sagonline.render.triton_vote_chunk import vote_chunks

    chosen = {"count": "chunk16", "blend": "walk"}
    monkeypatch.setattr(vote_op, "triton_vote_kernel", lambda weighting, k: chosen[weighting])
    count, blend = (vote_op.implementation("triton", w, 3) for w in ("count", "blend"))
    assert count.keywords["launch"].func is vote_chunks
    assert count.keywords["launch"].keywords == {"chunk": 16, "warps": 8}
    assert "launch" not in blend.keywords
    assert backends.TRITON_VOTE_KERNELS["chunk16"] == (16, 8)


@pytest.mark.slow
def test_the_blend_bound_takes_another_rounding_and_refuses_a_wrong_walk(monkeypatch):
    """The bound accepts the weights of another correct float32 evaluation (alpha from a
    float64 evaluation, rounded: what fused multiply-adds and another exp do on a GPU; it moves
    a few weights by up to 5e-4 relative, which rtol 1e-5 refused) and refuses a walk that
    weighs each pair by T after it instead of before it."""
    import sys

    from sagonline.render import _torch_impl

    rasterize_module = sys.modules["sagonline.render.rasterize"]
    response = rasterize_module.splat_response
    g, cams = _scene_views("2dgs", 0, 3000, 320, 240)
    cam, labels, rule = cams[2], _masks(cams[2], 4, 0), RULES["blend"]
    exact, bound = blend_bound(g, cam, labels, 4, rule)

    def rounded_from_float64(kind, params, px, py):
        alpha, depth, dist2 = response(kind, params.double(), px.double(), py.double())
        return alpha.float(), depth.float(), dist2.float()

    with monkeypatch.context() as m:
        m.setattr(rasterize_module, "splat_response", rounded_from_float64)
        other = vote_histogram(g, cam, labels, 4, rule, backend="torch")
    assert not torch.isclose(other, exact, rtol=1e-5, atol=1e-7).all()  # rtol 1e-5 refused it
    assert ((other - exact).abs() <= bound).all()

    def t_after(hist, flat, chunk, weighting):
        index = chunk.gaussian * hist.shape[1] + flat[chunk.pixel]
        w = chunk.alpha * chunk.transmittance * (1 - chunk.alpha)
        hist.view(-1).scatter_add_(0, index, w.double())
        return int(index.numel())

    monkeypatch.setattr(_torch_impl, "add_pairs", t_after)
    wrong = vote_histogram(g, cam, labels, 4, rule, backend="torch")
    assert ((wrong - exact).abs() > bound).sum() > 1000


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available() or not HAS_TRITON, reason="needs CUDA, triton")
@pytest.mark.parametrize("case", list(KERNEL_CASES))
@pytest.mark.parametrize("kernel", TRITON_VOTE_KERNELS)
def test_triton_on_cuda_matches_the_reference(case, kernel, monkeypatch):
    monkeypatch.setenv("SAGONLINE_TRITON_VOTE", kernel)
    _check_kernel_case(case, "cuda", views=3)
    if kernel != "walk":  # the composite walk is one kernel: checked once
        return
    kind, n, width, height = KERNEL_CASES[case]
    g, cams = _scene_views(kind, 0, n, width, height)
    for cam in cams:
        _check_image_walk(g.to("cuda"), cam.to("cuda"))
