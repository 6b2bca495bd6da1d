"""`make tables [DATASET=mold_cape]`: every job a table target would launch composes into a
valid config, on the data and mask sources the target promises."""

from __future__ import annotations

import itertools
import shlex
import shutil
import subprocess

import pytest

from tests.fixtures import ROOT, compose_config

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs make")


def planned_jobs(*make_args: str) -> list[tuple[list[str], str]]:
    """(overrides, output folder) of every bench.runners.eval job `make -n` prints, sweeps
    expanded."""
    out = subprocess.run(
        ["make", "-n", "-o", ".venv/.installed", "-o", ".venv/.extras", *make_args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.replace("\\\n", " ")
    jobs = []
    for command in (c for line in out.splitlines() for c in line.split("&&")):
        words = shlex.split(command)
        if "bench.runners.eval" not in words:
            continue
        args = words[words.index("bench.runners.eval") + 1 :]
        folder = next(a.split("=", 1)[1] for a in args if a.startswith("hydra."))
        args = [a for a in args if a != "--multirun" and not a.startswith("hydra")]
        choices = [[f"{a.split('=')[0]}={v}" for v in a.split("=", 1)[1].split(",")] for a in args]
        jobs += [(list(combo), folder) for combo in itertools.product(*choices)]
    return jobs


def one_per_folder(jobs: list[tuple[list[str], str]]) -> list[tuple[list[str], str]]:
    """A sweep's jobs differ only in the swept values: one composed job per output folder
    checks its data and mask source (composing all 63 took 30 s)."""
    return list({folder: (overrides, folder) for overrides, folder in jobs}.values())


@pytest.mark.slow
def test_the_real_capture_tables_run_both_mask_sources_on_one_protocol():
    jobs = planned_jobs("tables", "DATASET=mold_cape")
    # timing 1, masks 2 x 8, ablation 2 x 14, robustness 2 x 9
    assert len(jobs) == 1 + 16 + 28 + 18
    assert all("dataset=mold_cape" in overrides for overrides, _ in jobs)
    sources = set()
    for overrides, folder in one_per_folder(jobs):
        cfg = compose_config("eval", *overrides)
        assert cfg.dataset["name"] == "mold_cape" and cfg.dataset["adapter"]["exclude_reference"]
        assert "_mold_cape/" in folder
        source = (cfg.segmenter["name"], cfg.consensus.stride)
        sources.add(source)
        if "/robustness_" in folder:
            assert cfg.segmenter.get("flicker", 0) == 0  # corrupt.* degrades, not the oracle
    assert sources == {("oracle", 4), ("oracle", 1), ("classical", 1)}


@pytest.mark.slow
def test_the_default_tables_stay_on_the_synthetic_scenes():
    jobs = planned_jobs("tables")
    assert len(jobs) == 1 + 8 + 14 + 9
    names = {compose_config("eval", *o).dataset["name"] for o, _ in one_per_folder(jobs)}
    assert names == {"synthetic_360", "synthetic_360_hd"}
    assert all("_mold_cape" not in folder for _, folder in jobs)
