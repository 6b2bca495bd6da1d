"""Hydra's options anywhere on a command line: `make eval ARGS="--multirun ..."` puts
`dataset=...` before them, and Hydra's parser takes no override after an option that follows
one."""

from __future__ import annotations

import subprocess
import sys

import pytest

from bench.runners.overrides import options_first
from tests.fixtures import ROOT


@pytest.mark.parametrize(
    ("argv", "ordered"),
    [
        (["dataset=x", "--multirun", "a=1,2"], ["--multirun", "dataset=x", "a=1,2"]),
        (["a=1", "--cfg", "job", "b=2"], ["--cfg", "job", "a=1", "b=2"]),
        (["x=1", "--info", "defaults", "y=2"], ["--info", "defaults", "x=1", "y=2"]),
        (["x=1", "--info", "y=2"], ["--info", "x=1", "y=2"]),  # --info without its word
        (["a=1", "--config-name=eval", "-m", "~b"], ["--config-name=eval", "-m", "a=1", "~b"]),
        (["a=1", "-cn", "eval", "c=-1"], ["-cn", "eval", "a=1", "c=-1"]),
        (["--multirun", "a=1"], ["--multirun", "a=1"]),
        ([], []),
    ],
)
def test_hydras_options_go_before_the_overrides_each_in_its_order(argv, ordered):
    assert options_first(argv) == ordered


@pytest.mark.parametrize("command", ["bench.runners.eval", "bench.runners.scenes"])
def test_an_override_after_an_option_reaches_the_config(command):
    """As `make eval` writes a sweep: an override, an option, then overrides."""
    key = "consensus.eps=0.05" if command.endswith("eval") else "fit.iterations=7"
    proc = subprocess.run(
        [sys.executable, "-m", command, "dataset=synthetic_ff", "--cfg", "job", key],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    path, value = key.split("=")
    assert "name: synthetic_ff" in proc.stdout and f"  {path.split('.')[-1]}: {value}\n" in (
        proc.stdout
    )
