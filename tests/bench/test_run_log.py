"""The run's log: every record in eval.log, each message once on the console."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys

from bench.runners.runlog import run_log
from sagonline.pipeline.evaluate import FILE_ONLY
from tests.fixtures import ROOT, shared_data


def test_a_file_only_record_stays_off_every_console(tmp_path, monkeypatch, capsys):
    """Records logged with FILE_ONLY (what the console is told in words of its own) reach
    eval.log alone: off a console handler that was there (Hydra's) and off the one the log
    adds where there was none; a plain warning reaches both."""
    root = logging.getLogger()
    for there in (False, True):
        hydra = io.StringIO()
        monkeypatch.setattr(root, "handlers", [logging.StreamHandler(hydra)] if there else [])
        capsys.readouterr()
        with run_log(tmp_path / str(there)):
            logging.getLogger("sagonline.eval").warning("said in words", extra=FILE_ONLY)
            logging.getLogger("sagonline.eval").warning("a plain warning")
        console = hydra.getvalue() if there else capsys.readouterr().err
        assert "said in words" not in console and "a plain warning" in console, console
        log = (tmp_path / str(there) / "eval.log").read_text()
        assert "said in words" in log and "a plain warning" in log


def test_a_scene_that_cannot_load_is_said_once_on_the_console(tmp_path):
    """A scene without its trained Gaussians: its reason once as a warning (Hydra's log line
    said it again on the standard output, as did the error), once under its row of the table,
    and in eval.log; exit status 1, and the overall line says no scene was scored (it said
    "PARTIAL: some scenes failed")."""
    shared_data("mold_cape")
    env = {**os.environ, "SAGONLINE_SCENES": str(tmp_path / "no scenes")}
    run = tmp_path / "run"
    args = ["dataset=mold_cape", f"hydra.run.dir={run}", "record=false", "progress=false"]
    proc = subprocess.run(
        [sys.executable, "-m", "bench.runners.eval", *args, "cache_dir=null"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 1, proc.stderr
    said = proc.stderr.splitlines() + proc.stdout.splitlines()  # the console, both streams
    reason = [line for line in said if "no trained scene for mold_cape" in line]
    assert [line.split(":")[0] for line in reason] == [
        "warning",
        "    no trained scene for mold_cape",
    ]
    assert sum(line.startswith("error: no scene was scored") for line in said) == 1, said
    assert not any("records why" in line for line in said), said  # the log's line, in the log
    assert "overall mIoU -  mAcc -  segmenter mIoU -   (FAILED: no scene was scored)" in said
    assert "no trained scene for mold_cape" in (run / "eval.log").read_text()
