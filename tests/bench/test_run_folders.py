"""Run folders: read-only, locked, overwritten or refused runs; the report skips a bad metrics
file; nothing the harness did not write is lost."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.runners.eval import evaluate
from bench.runners.rundir import RunExists
from sagonline.apps.cli import main
from tests.fixtures import (
    ROOT,
    TINY,
    cfg_with,
)
from tests.refusals import (
    error_line,
)


def test_read_only_run_folder_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff"), blocker / "run")  # cannot be created
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "cannot be written" in err and str(blocker) in err


def test_report_skips_a_bad_metrics_file_and_names_it(tmp_path, capsys):
    from bench.tables.report import main

    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), tmp_path / "runs" / "good")
    for name, text in (("truncated", '{"dataset": "x", "sce'), ("empty", "{}")):
        (tmp_path / "runs" / name).mkdir()
        (tmp_path / "runs" / name / "metrics.json").write_text(text)
    main([str(tmp_path / "runs"), "--out", str(tmp_path / "reports")])
    err = capsys.readouterr().err
    assert "truncated/metrics.json: unreadable" in err and "empty/metrics.json: lacks" in err
    rows = (tmp_path / "reports" / "runs.csv").read_text().strip().splitlines()
    assert len(rows) == 2  # header + the good run, no row of blanks


@pytest.mark.slow
def test_an_overwritten_run_folder_keeps_nothing_of_the_old_config(tmp_path):
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    evaluate(cfg_with("dataset=synthetic_ff", "record=true"), run)
    assert main(["export", str(run), "--out", str(run / "export")]) == 0  # one's own choice
    assert (run / "export").is_dir() and (run / "recording.rrd").is_file()
    evaluate(
        cfg_with("dataset=synthetic_ff", "record=false", "consensus.eps=0.1", "overwrite=true"), run
    )
    assert not (run / "export").exists() and not (run / "recording.rrd").exists()
    assert json.loads((run / "metrics.json").read_text())["consensus"]["eps"] == 0.1
    assert not list(tmp_path.glob(".run.replaced-*"))


def test_a_second_run_into_a_locked_folder_is_refused(tmp_path, capsys):
    from bench.runners.eval import evaluate
    from sagonline.core.outputs import RunLock

    run = tmp_path / "run"
    with RunLock(run), pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    assert exc.value.code == 2
    error_line(capsys, "another run is writing into this folder")
    assert not (run / "metrics.json").exists()


@pytest.mark.slow
def test_a_refused_run_leaves_no_folder(tmp_path):
    run = tmp_path / "run"
    done = subprocess.run(
        [sys.executable, "-m", "bench.runners.eval", "consensus.eps=2", f"hydra.run.dir={run}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "consensus.eps=2.0" in done.stderr
    assert not run.exists()


def test_overwrite_replaces_only_what_the_harness_wrote(tmp_path, capsys):
    """A file of the user's in a finished run folder survives overwrite=true, and is named
    (it was moved aside and deleted with the old run)."""
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    (run / "notes.txt").write_text("why this run matters")
    (run / "mine").mkdir()
    evaluate(
        cfg_with("dataset=synthetic_ff", "record=false", "consensus.eps=0.1", "overwrite=true"), run
    )
    assert (run / "notes.txt").read_text() == "why this run matters" and (run / "mine").is_dir()
    assert "kept what the harness did not write: mine, notes.txt" in capsys.readouterr().err


def _bench_eval(*args, cwd=ROOT, **kw):
    cmd = [sys.executable, "-m", "bench.runners.eval", *args, "progress=false", *TINY]
    return subprocess.Popen(
        cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw
    )


def _snapshot(run_dir: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(run_dir)): p.read_bytes()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file() and "cache" not in p.parts
    }


@pytest.mark.slow
def test_killed_sweep_resumes_and_finished_jobs_stay_byte_identical(tmp_path):
    sweep = tmp_path / "sweep"
    args = [
        "--multirun",
        "consensus.eps=0.01,0.1,0.5",
        "dataset=synthetic_ff",
        "record=false",
        f"hydra.sweep.dir={sweep}",
    ]
    proc = _bench_eval(*args)
    while not (sweep / "1" / "metrics.json").exists():  # bounded by the sweep itself
        assert proc.poll() is None, proc.stdout.read()
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(300)
    assert not (sweep / "2" / "metrics.json").exists()
    before = {j: _snapshot(sweep / j) for j in ("0", "1")}
    sweep_file = (sweep / "multirun.yaml").read_bytes()

    out, _ = _bench_eval(*args).communicate(timeout=300)
    assert out.count("already holds this run") == 2, out
    assert (sweep / "2" / "metrics.json").is_file()
    assert {j: _snapshot(sweep / j) for j in ("0", "1")} == before
    assert (sweep / "multirun.yaml").read_bytes() == sweep_file
    # a sweep with other values into the same folder is refused and changes nothing
    other = _bench_eval(*[a.replace("0.01,0.1,0.5", "0.2,0.3") for a in args])
    out, _ = other.communicate(timeout=300)
    assert other.returncode == 2 and "other overrides" in out
    assert {j: _snapshot(sweep / j) for j in ("0", "1")} == before
    assert (sweep / "multirun.yaml").read_bytes() == sweep_file

    from bench.tables.paper import build

    df = build("ablation", sweep, tmp_path / "reports")
    labels = dict(zip(df["eps"], df["overrides"], strict=True))
    for eps, label in labels.items():
        assert f"consensus.eps={eps:g}" in label


@pytest.mark.slow
def test_refused_rerun_leaves_the_finished_run_untouched(tmp_path):
    run = tmp_path / "run"
    proc = _bench_eval("dataset=synthetic_ff", f"hydra.run.dir={run}")
    assert proc.wait(300) == 0
    before = _snapshot(run)
    assert {".hydra/config.yaml", ".hydra/overrides.yaml", "metrics.json", "eval.log"} <= set(
        before
    )
    assert b"summary" in before["eval.log"]
    from sagonline.core.files import _umask

    assert (run / "metrics.json").stat().st_mode & 0o777 == 0o666 & ~_umask()
    metrics = json.loads(before["metrics.json"])
    assert metrics["status"] == "complete" and metrics["git"]["commit"]
    assert "dataset=synthetic_ff" in metrics["overrides"]
    refused = _bench_eval("dataset=synthetic_ff", "consensus.eps=0.1", f"hydra.run.dir={run}")
    out, _ = refused.communicate(timeout=300)
    assert refused.returncode == 2
    assert "consensus.eps: 0.01 -> 0.1" in out and "Nothing was changed" in out
    assert _snapshot(run) == before


def test_interrupt_keeps_a_recording_of_what_was_done(tmp_path, monkeypatch):
    import bench.runners.eval
    from sagonline.vote.consensus import VoteAccumulator

    add_view, votes = VoteAccumulator.add_view, []

    def stop(self, *args, **kwargs):  # the third view's vote is interrupted
        votes.append(1)
        if len(votes) == 3:
            raise KeyboardInterrupt
        return add_view(self, *args, **kwargs)

    monkeypatch.setattr(VoteAccumulator, "add_view", stop)
    with pytest.raises(KeyboardInterrupt):
        bench.runners.eval.evaluate(cfg_with("dataset=synthetic_ff"), tmp_path)
    assert not (tmp_path / "metrics.json").exists()
    # the frames and masks rendered before the interrupt are in the recording
    assert (tmp_path / "recording.rrd").stat().st_size > 20_000


def test_refusal_is_a_run_exists(tmp_path):
    evaluate(cfg_with("record=false", "dataset=synthetic_ff"), tmp_path)
    with pytest.raises(RunExists):
        evaluate(cfg_with("record=false", "dataset=synthetic_ff", "seed=1"), tmp_path)


def test_a_metrics_json_that_is_no_object_is_named(tmp_path, capsys):
    """A finished-looking run folder whose metrics.json holds a list: one line naming the file,
    exit 2 (it was a traceback)."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text("[1, 2]")
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff"), run)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "metrics.json: holds a list, not a JSON object" in err and err.count("\n") == 1


def test_a_skipped_run_made_by_other_code_says_so(tmp_path, capsys):
    """Rerunning a finished run skips it; where its metrics.json records another commit (and
    other stage versions) than this checkout's, the skip says so and how to rerun it."""
    from bench.runners.eval import evaluate
    from bench.runners.rundir import code_difference
    from sagonline.score.run_metrics import RunMetrics

    run = tmp_path / "run"
    cfg = cfg_with("dataset=synthetic_ff", "record=false")
    evaluate(cfg, run)
    capsys.readouterr()
    evaluate(cfg, run)
    out = capsys.readouterr().out
    assert "already holds this run" in out and "made at commit" not in out
    record = json.loads((run / "metrics.json").read_text())
    if not record["git"].get("commit"):
        pytest.skip("not a git checkout: no commit to compare")
    record["git"]["commit"] = "0123456789" * 4
    stage = next(iter(record["stage_versions"]))
    record["stage_versions"][stage] = -1
    (run / "metrics.json").write_text(json.dumps(record))
    evaluate(cfg, run)
    out = capsys.readouterr().out
    assert "already holds this run" in out
    assert "made at commit 0123456789, this checkout is" in out
    assert f"stage versions {stage} -1 -> " in out and "overwrite=true reruns it" in out
    previous = RunMetrics.read(run / "metrics.json")
    assert code_difference(previous, {"commit": None}, {}) == ""  # no git here: say nothing


def test_a_finished_run_of_another_protocol_version_is_never_taken_for_this_one(tmp_path, capsys):
    """A finished run scored by another protocol version (same config and inputs) is neither
    skipped as this run, whose numbers would then be the old rule's, nor replaced: the rerun
    stops naming both ids, and the run's files are as they were."""
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    cfg = cfg_with("dataset=synthetic_ff", "record=false")
    evaluate(cfg, run)
    record = json.loads((run / "metrics.json").read_text())
    record["protocol_id"] = record["protocol_id"].replace("@1", "@0")
    (run / "metrics.json").write_text(json.dumps(record))
    before = (run / "metrics.json").read_bytes()
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg, run)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert "scored by protocol synthetic/held-out-views@0; this code scores " in err
    assert "synthetic/held-out-views@1" in err and "overwrite=true" in err
    assert (run / "metrics.json").read_bytes() == before
