"""Fixtures shared by every test (helpers themselves: tests/fixtures.py)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# The Triton kernels run on the CPU in Triton's interpreter, which Triton fixes when it is first
# imported: choose it before any test (or library) imports triton.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

# Under pytest-xdist (`make test` runs one worker per core) each worker keeps torch to one
# thread: two workers of two threads each on two cores collapse torch's thread pool.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)

from tests.fixtures import random_gaussians

TEST_HOME = pytest.StashKey[Path]()


def pytest_configure(config) -> None:
    """The suite writes only below a temporary folder: caches that default to the home folder
    (the file digests' memo, matplotlib's, YOLO's settings, XDG caches) go to one of the run's
    own, for this process and every process it starts; removed when the process ends
    (`pytest_unconfigure`; under pytest-xdist each worker has its own)."""
    import tempfile

    home = Path(tempfile.mkdtemp(prefix="sagonline-tests-home-"))
    config.stash[TEST_HOME] = home
    for var, sub in (
        ("SAGONLINE_DIGEST_CACHE", "digests.json"),
        ("XDG_CACHE_HOME", "cache"),
        ("MPLCONFIGDIR", "matplotlib"),
        ("YOLO_CONFIG_DIR", "yolo"),
    ):
        os.environ[var] = str(home / sub)
    os.environ["HOME"] = str(home)
    try:  # its example database too (it defaults to ./.hypothesis); a GPU machine has none
        from hypothesis import settings
        from hypothesis.database import DirectoryBasedExampleDatabase
    except ModuleNotFoundError:
        return

    settings.register_profile(
        "sagonline", database=DirectoryBasedExampleDatabase(str(home / "hypothesis"))
    )
    settings.load_profile("sagonline")


def pytest_unconfigure(config) -> None:
    """The run's home folder goes (tens of MB of caches a run, left in /tmp otherwise)."""
    import shutil

    home = config.stash.get(TEST_HOME, None)
    if home is not None:
        shutil.rmtree(home, ignore_errors=True)


def pytest_collection_modifyitems(config, items) -> None:
    """The `slow` tests run first (in their order, then the rest in theirs): with a worker per
    core, the longest ones (the GPU check's, a minute or more) starting last would leave one
    worker busy while the other has nothing left."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="module")
def tiny_task():
    """The forward-facing synthetic preset at 40x30: 1,500 Gaussians, 5 trajectory views, 2
    eval views (read-only: tests pass it to the pipeline, never change it)."""
    from sagonline.datasets.synthetic import load_synthetic

    return load_synthetic(
        preset="forward_single",
        layout="forward",
        num_gaussians=1500,
        width=40,
        height=30,
        num_train_views=5,
        num_eval_views=2,
    )[0]


@pytest.fixture
def tiny_scene():
    return random_gaussians(30, "3dgs", seed=1)


@pytest.fixture(autouse=True)
def _no_global_hydra_leaks():
    """Importing sam2 (even through pytest.importorskip) initialises Hydra globally; clear it
    so the next test can compose configs."""
    yield
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
