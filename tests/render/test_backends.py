"""Backend and device resolution, the CUDA branches included, on any machine: what is installed
is an `Installed` the test chooses, and `torch.device("cuda")` needs no GPU to exist."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.render.backends import (
    BackendError,
    Installed,
    installed,
    plan_backends,
    resolve_backend,
    resolve_vote_backend,
)

EVERYTHING = dict(cuda=True, gsplat=True, triton=True, native=True)


def have(**changes) -> Installed:
    return Installed(**{**EVERYTHING, **changes})


@pytest.mark.parametrize(
    ("what", "images", "vote"),
    [
        ({}, "gsplat", "triton"),
        # the H100 without gsplat: the fused walk votes and renders the images
        ({"gsplat": False}, "triton", "triton"),
        ({"triton": False}, "gsplat", "gsplat"),
        ({"gsplat": False, "triton": False}, "torch", "torch"),
    ],
)
@pytest.mark.parametrize("device", ["cuda", "cuda:1", torch.device("cuda", 0)])
def test_auto_on_cuda_resolves_images_and_the_vote_each_on_its_own(what, images, vote, device):
    plan = plan_backends("auto", "auto", device, have(**what))
    assert (plan.images, plan.vote, plan.labels) == (images, vote, vote)
    assert plan.describe()["images"] == images


@pytest.mark.parametrize(("native", "expected"), [(True, "native"), (False, "torch")])
def test_auto_on_the_cpu_takes_the_compiled_kernel_where_it_builds(native, expected):
    plan = plan_backends("auto", "auto", "cpu", have(cuda=False, native=native))
    assert (plan.device, plan.images, plan.vote) == ("cpu", expected, expected)


def test_auto_device_picks_the_gpu_only_when_there_is_one():
    assert plan_backends("auto", "auto", "auto", have()).device == (
        "cuda" if torch.cuda.is_available() else "cpu"
    )


@pytest.mark.parametrize(
    ("call", "words"),
    [
        (lambda h: resolve_backend("gsplat", "cpu", h), "CUDA only"),
        (lambda h: resolve_backend("native", "cuda", h), "CPU kernel"),
        (lambda h: resolve_backend("gsplat", "cuda", have(gsplat=False)), ".[gsplat]"),
        (lambda h: resolve_vote_backend("triton", "cuda", have(triton=False)), ".[triton]"),
        (lambda h: resolve_vote_backend("gsplat", "cpu", h), "CUDA only"),
        (lambda h: resolve_vote_backend("native", "cuda:0", h), "CPU kernel"),
        (lambda h: resolve_vote_backend("fast", "cpu", h), "not one of"),
        (lambda h: resolve_backend("triton", "cuda", have(triton=False)), ".[triton]"),
        (lambda h: resolve_backend("fast", "cuda", h), "not one of"),
    ],
)
def test_a_backend_that_cannot_run_is_refused_naming_what_to_do(call, words):
    with pytest.raises(BackendError, match=words.replace(".", r"\.").replace("[", r"\[")):
        call(have())


def test_a_named_backend_is_taken_as_asked():
    assert resolve_vote_backend("torch", "cuda", have()) == "torch"
    assert resolve_vote_backend("triton", "cpu", have(cuda=False)) == "triton"  # interpreter
    assert resolve_backend("torch", "cuda", have()) == "torch"


def test_probes_run_once_and_only_when_asked():
    calls = []
    h = Installed(cuda=True)
    h._probes["triton"] = lambda: calls.append("triton") or True
    h._probes["native"] = lambda: calls.append("native") or True
    assert resolve_vote_backend("auto", "cuda", h) == "triton"
    assert resolve_vote_backend("auto", "cuda", h) == "triton"
    assert calls == ["triton"]  # the CPU kernel is never built for a CUDA run


def test_this_machines_probes_answer():
    """The real probes (imports included) run here: a missing name in them fails this test,
    not a user's first `device=cuda` run."""
    here = installed()
    for what in ("cuda", "gsplat", "triton"):
        assert isinstance(here.has(what), bool)
    real = Installed(cuda=True, native=False)  # this machine's packages, as if it had a GPU
    assert resolve_vote_backend("auto", "cuda", real) in ("triton", "gsplat", "torch")
    assert resolve_backend("auto", "cuda", real) in ("gsplat", "torch")


def test_the_pipeline_votes_with_its_own_backend(monkeypatch):
    """Stage I's engine takes its backends from one plan: the frames render with the plan's
    image renderer and the views vote with its vote backend (on CUDA without gsplat: torch and
    triton), never the image renderer's choice. Run here with a CPU plan of two backends."""
    from sagonline.pipeline import stage_one
    from sagonline.render.backends import BackendPlan
    from sagonline.vote import consensus

    monkeypatch.setattr(
        stage_one, "plan_backends", lambda *a: BackendPlan("cpu", "torch", "native", "native")
    )
    used = {"images": set(), "vote": set()}
    render, vote_into = stage_one.render, consensus.vote_into

    def spy_render(*args, backend, **kw):
        used["images"].add(backend)
        return render(*args, backend=backend, **kw)

    def spy_vote(*args, backend, **kw):
        used["vote"].add(backend)
        return vote_into(*args, backend=backend, **kw)

    monkeypatch.setattr(stage_one, "render", spy_render)
    monkeypatch.setattr(consensus, "vote_into", spy_vote)
    g, cams, prompt, run, vote = _tiny_stage_one_inputs()
    gt = [np.ones((6, 8), np.int64)]
    engine = stage_one.StageOne(
        stage_one.StageOneConfig(g, cams, run, vote, trajectory_gt=gt), prompt
    )
    out = engine.run()
    assert used == {"images": {"torch"}, "vote": {"native"}}
    assert out.backends.describe() == {
        "device": "cpu",
        "images": "torch",
        "vote": "native",
        "labels": "native",
    }


def _tiny_stage_one_inputs():
    from sagonline.pipeline.stages import SegmenterRun
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.segment.prompts import ObjectPrompt, Prompt
    from sagonline.vote.consensus import VoteConfig
    from tests.fixtures import random_gaussians, small_camera

    g = random_gaussians(20, "3dgs")
    cam = small_camera(8, 6)
    prompt = Prompt(frame=0, objects=[ObjectPrompt(label=1, mask=np.ones((6, 8), bool))])
    return g, [cam], prompt, SegmenterRun(OracleSegmenter()), VoteConfig()


def _gsplat_everywhere(monkeypatch) -> list[str]:
    """Simulate gsplat installed on the CPU: the resolution answers gsplat, and gsplat's
    function renders with `rasterize` (no ids) noting each call in the returned list."""
    from sagonline.pipeline import scene as scene_module
    from sagonline.render import api

    calls = []

    def fake_gsplat(
        gaussians,
        camera,
        *,
        background=None,
        features=None,
        trace=None,
        near=0.01,
        tile_size=16,
        batch=32,
    ):
        calls.append("gsplat")
        return api.rasterize(gaussians, camera, background=background, features=features)

    real = api._backend_function
    for module in (api, scene_module):
        monkeypatch.setattr(module, "resolve_backend", lambda backend, device: "gsplat")
    monkeypatch.setattr(
        api, "_backend_function", lambda name: fake_gsplat if name == "gsplat" else real(name)
    )
    return calls


def test_a_render_that_needs_ids_takes_a_backend_that_draws_them(monkeypatch):
    """With gsplat installed (the usual GPU setup) `auto` and `gsplat` render images with gsplat,
    which draws no ids: the per-view diagnosis asks for ids and gets them from another backend
    (triton on CUDA, the compiled kernel or torch on the CPU), never a refusal. Simulated on
    the CPU: the resolution answers gsplat, gsplat's function is a stub that must not be
    called for ids."""
    from sagonline.render import api
    from sagonline.render.backends import _device_type
    from tests.fixtures import random_gaussians, small_camera

    calls = _gsplat_everywhere(monkeypatch)
    g, cam = random_gaussians(200, seed=3), small_camera(32, 24)
    out = api.render(g, cam, backend="auto", return_ids=True)
    assert out.ids is not None and out.ids.shape == (24, 32) and calls == []
    api.render(g, cam, backend="gsplat")  # images alone: gsplat's
    assert calls == ["gsplat"]
    on = "cuda" if _device_type(g.means.device) == "cuda" else "cpu"
    assert api.capable_backend("gsplat", {"return_ids": True}, on) in ("native", "torch")
    assert api.capable_backend("gsplat", {"return_ids": True}, "cuda") in ("triton", "torch")


def test_an_eval_view_with_gsplat_keeps_its_colours_and_takes_ids_elsewhere(monkeypatch):
    """The eval views' render (diagnosed and recorded from one render where the images backend
    draws ids): with gsplat, the ids come from another backend and the colours stay gsplat's,
    as the recording showed them before; without ids, one gsplat render."""
    from sagonline.pipeline.scene import eval_render
    from sagonline.render import api
    from tests.fixtures import random_gaussians, small_camera

    calls = _gsplat_everywhere(monkeypatch)
    g, cam = random_gaussians(200, seed=5), small_camera(32, 24)
    white = torch.ones(3)
    out = eval_render(g, cam, white, "auto", ids=True)
    gsplat = api.rasterize(g, cam, background=white)
    assert calls == ["gsplat"] and out.ids is not None and out.ids.shape == (24, 32)
    assert torch.equal(out.rgb, gsplat.rgb)
    assert torch.equal(out.ids, api.rasterize(g, cam, return_ids=True).ids)
    assert eval_render(g, cam, white, "auto", ids=False).ids is None and len(calls) == 2


def test_an_installed_backend_can_be_hidden_for_a_run(monkeypatch):
    """SAGONLINE_WITHOUT=gsplat runs as a machine without gsplat does (gpu_check.sh evaluates
    both ways on one machine)."""
    monkeypatch.setenv("SAGONLINE_WITHOUT", "gsplat,triton")
    fresh = Installed()
    assert not fresh.has("gsplat") and not fresh.has("triton")
    monkeypatch.setenv("SAGONLINE_WITHOUT", "")
    assert Installed().has("triton") == (
        __import__("importlib").util.find_spec("triton") is not None
    )
