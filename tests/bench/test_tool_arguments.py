"""The runners' arguments refused before any work, each in one line naming what to fix: true/false
settings given numbers, fit variants that are paths, a leave-one-out candidate or a fit recipe
that names the capture, an unknown capture, a missing fit's cause, a quote in CANDIDATES, a
full disk."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bench.runners import captures, fit_captures, real
from sagonline.core.plugins import SEGMENTERS, PluginError
from tests.fixtures import ROOT


def run(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=300, **kw
    )


def test_a_number_for_a_true_false_setting_is_refused(tmp_path):
    done = run(
        "bench.runners.eval",
        "dataset=synthetic_ff",
        "consensus.body=2",
        f"hydra.run.dir={tmp_path / 'r'}",
    )
    assert done.returncode == 2 and "consensus.body=2: must be true or false" in done.stderr
    assert not (tmp_path / "r" / "metrics.json").exists()
    with pytest.raises(PluginError, match="use_masks=2: must be true or false"):
        SEGMENTERS.build("sam2", {"use_masks": 2})


def test_a_fit_variant_is_a_plain_name_never_a_path(tmp_path):
    done = run(
        "bench.runners.scenes",
        "dataset=mold_cape",
        "variant=x/../../../escape",
        f"hydra.run.dir={tmp_path / 's'}",
    )
    assert done.returncode == 2 and "scenes.variant='x/../../../escape'" in done.stderr
    done = run(
        "bench.runners.eval",
        "dataset=mold_cape",
        "dataset.adapter.fit=x/../..",
        f"hydra.run.dir={tmp_path / 'e'}",
    )
    assert done.returncode == 2 and "dataset.adapter.fit='x/../..'" in done.stderr


def test_the_cross_capture_tools_keep_the_capture_and_seed_their_own(capsys):
    for argv, said in [
        (["--settings", "dataset=mold_cape consensus.body=true"], "'dataset=mold_cape'"),
        (["--settings", "seed=3"], "'seed=3'"),
        (["--captures", "nope"], "--captures 'nope': nope: not a capture here"),
        (["--jobs", "1000"], "--jobs 1000: 1 to"),
    ]:
        with pytest.raises(SystemExit) as exc:
            real.main(argv)
        assert exc.value.code == 2 and said in capsys.readouterr().err
    for argv, said in [
        (["dataset.root=/tmp"], "dataset.root=/tmp"),
        (["hydra.run.dir=/"], "hydra.run.dir=/"),
        (["--jobs", "1000"], "1 to"),
    ]:
        with pytest.raises(SystemExit) as exc:
            fit_captures.main(["--dry-run", *argv])
        assert exc.value.code == 2 and said in capsys.readouterr().err


def test_a_missing_fit_is_said_with_its_cause(monkeypatch, capsys):
    monkeypatch.setattr(
        captures, "fit_and_problem", lambda c, s, st=(): (None, "no trained scene X")
    )
    with pytest.raises(SystemExit):
        real.main(["--captures", "mold_cape", "--seeds", "0", "--sources", "real"])
    assert "mold_cape/seed 0: no fit: no trained scene X" in capsys.readouterr().err


def test_a_quote_in_candidates_stays_a_string(tmp_path):
    """make loo-captures passes CANDIDATES through the environment: a double quote in it is
    text, never the end of a shell string."""
    stub = tmp_path / "bin"
    stub.mkdir()
    (stub / "python").write_text('#!/bin/sh\nprintf "%s\\n" "$@" > "$OUT_FILE"\n')
    (stub / "python").chmod(0o755)
    marker = tmp_path / "pwned"
    candidates = f'x"; touch {marker}; echo "'
    env = {**os.environ, "OUT_FILE": str(tmp_path / "argv")}
    done = subprocess.run(
        [
            "make",
            "-o",
            "install",
            "-o",
            "weights",
            "loo-captures",
            f"BIN={stub}",
            f"CANDIDATES={candidates}",
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert not marker.exists()
    assert candidates in (tmp_path / "argv").read_text().splitlines()


def test_a_full_disk_is_one_line_naming_the_file(tmp_path):
    done = subprocess.run(
        [
            "bash",
            "-c",
            f"ulimit -f 1; exec {sys.executable} -m bench.runners.eval dataset=synthetic_ff "
            f"record=false cache_dir=null hydra.run.dir={tmp_path / 'r'}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines[-1].startswith("error: cannot write ") and "ulimit -f" in lines[-1]
    assert "Traceback" not in done.stderr


def test_export_says_when_the_run_read_other_weights():
    from sagonline.pipeline.recorded import other_weights

    assert (
        other_weights(
            {"/a/encoder.onnx": "1", "/a/sam.onnx": "2"},
            {"/b/encoder.onnx": "1", "/b/sam.onnx": "2"},
        )
        == []
    )
    said = other_weights({"/a/encoder.onnx": "1"}, {"/b/encoder.onnx": "9"})
    assert said and "encoder.onnx" in said[0]


@pytest.mark.parametrize("threads", ["0", "two", "default,-1"])
def test_a_thread_count_that_is_not_default_or_positive_is_refused(threads, tmp_path):
    done = run("bench.speed.sam_host", "--threads", threads, "--out", str(tmp_path / "t.csv"))
    assert done.returncode == 2 and "--threads: 'default' or counts >= 1" in done.stderr
    assert not (tmp_path / "t.csv").exists()
