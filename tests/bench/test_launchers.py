"""The parallel launchers run the same code path as the basic one and give the same numbers:
joblib (`hydra/launcher=local`) and submitit's local executor (`slurm_local`, the code path
`LAUNCHER=slurm` takes on a cluster)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.fixtures import (
    ROOT,
    TINY,
)


def sweep(launcher: str, folder: Path) -> dict[str, dict]:
    cmd = [
        sys.executable,
        "-m",
        "bench.runners.eval",
        "--multirun",
        f"hydra/launcher={launcher}",
        "consensus.eps=0.01,0.1",
        "dataset=synthetic_ff",
        "record=false",
        "progress=false",
        f"hydra.sweep.dir={folder}",
        *TINY,
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    # the sweep's table, printed once its jobs have ended, whichever launcher ran them
    table = done.stdout[done.stdout.index(f"sweep {folder}: 2 job(s), 2 with a record") :]
    rows = [line.split()[:3] for line in table.splitlines()[2:4]]
    assert rows == [["0", "0.01", "complete"], ["1", "0.1", "complete"]], table
    out = {}
    for path in sorted(folder.glob("*/metrics.json")):
        m = json.loads(path.read_text())
        eps = m["consensus"]["eps"]
        out[eps] = {
            "miou": m["miou"],
            "macc": m["macc"],
            "labelled": m["scenes"][0]["vote"]["fraction_labelled"],
            "overrides": sorted(m["overrides"]),
            "threads": m["device"]["torch_threads"],
        }
    return out


@pytest.mark.slow
def test_joblib_and_submitit_local_match_the_basic_launcher(tmp_path):
    basic = sweep("basic", tmp_path / "basic")
    assert sorted(basic) == [0.01, 0.1]
    for launcher, threads in (("local", 1), ("slurm_local", 1)):
        got = sweep(launcher, tmp_path / launcher)
        for eps, row in basic.items():
            for key in ("miou", "macc", "labelled", "overrides"):
                assert got[eps][key] == row[key], (launcher, eps, key)
            assert got[eps]["threads"] == threads  # cores shared out, not oversubscribed
