"""Shared fixtures: tiny random scenes and cameras, and the path to the shared real data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from sagonline.cameras import intrinsics, look_at, make_camera
from sagonline.gaussians import Gaussians

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_data(*parts: str) -> Path:
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not found at {path} (the shared data folder sits beside the repo)")
    return path


def random_gaussians(
    n: int, kind: str = "3dgs", seed: int = 0, sh_degree: int = 1, spread: float = 1.0
) -> Gaussians:
    """n random Gaussians around the origin, sized to cover a few pixels of `small_camera`."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    k = (sh_degree + 1) ** 2
    dims = 3 if kind == "3dgs" else 2
    return Gaussians(
        means=torch.tensor(rng.uniform(-spread, spread, (n, 3)), dtype=torch.float32),
        quats=torch.tensor(q, dtype=torch.float32),
        scales=torch.tensor(rng.uniform(0.05, 0.35, (n, dims)), dtype=torch.float32),
        opacities=torch.tensor(rng.uniform(0.2, 0.98, n), dtype=torch.float32),
        sh=torch.tensor(rng.normal(scale=0.6, size=(n, k, 3)), dtype=torch.float32),
    )


def small_camera(width: int = 26, height: int = 19, eye=(0.3, -4.0, 0.8), name: str = "cam"):
    K = intrinsics(width * 1.1, width * 1.1, width / 2 + 0.3, height / 2 - 0.2)
    return make_camera(K, look_at(eye, (0, 0, 0)), width, height, name)


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
