"""The static check: mypy over sagonline/ and bench/ ([tool.mypy] in pyproject.toml) finds no
undefined name and no call whose arguments do not fit, the CUDA-only branches and the bench
scripts included, which no CPU test runs end to end (both crashes of the first GPU run were of
this kind: an import of a name that did not exist, a call missing an argument)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# one worker runs both (pytest-xdist --dist loadgroup), so the second reads the first's cache
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("mypy")]


@pytest.fixture(scope="module")
def mypy_cache(tmp_path_factory) -> Path:
    """One cache for both checks: the probe's imports are then read, not analysed again."""
    return tmp_path_factory.mktemp("mypy") / "cache"


def test_no_undefined_names_or_wrong_calls(mypy_cache):
    pytest.importorskip("mypy", reason="mypy is in the dev extras: pip install -e '.[dev]'")
    proc = subprocess.run(
        [sys.executable, "-m", "mypy", "--cache-dir", str(mypy_cache)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]


def test_the_check_catches_what_crashed_the_gpu_run(tmp_path, mypy_cache):
    """The same configuration on a file with both defects reports both."""
    pytest.importorskip("mypy", reason="mypy is in the dev extras: pip install -e '.[dev]'")
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from sagonline.render import vote_histogram\n"
        "from sagonline.render.triton_vote import triton_available\n"
        "def f():\n"
        "    vote_histogram(1, 2, 3, 4, backend='auto')\n"
        "    return triton_available\n"
    )
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mypy",
            "--cache-dir",
            str(mypy_cache),
            "--config-file",
            str(ROOT / "pyproject.toml"),
            str(probe),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 1
    assert "[attr-defined]" in proc.stdout and 'Missing positional argument "rule"' in proc.stdout
