"""Setting a job up before any work: seeds, threads, the device, the plug-ins, the settings
the library takes (each checked, a problem named in one line, exit 2)."""

from __future__ import annotations

import os
import random
import sys

import numpy as np
import torch

from sagonline.pipeline import PipelineSettings
from sagonline.refine import RefineConfig


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (legacy global RNG some plug-ins still use)
    torch.manual_seed(seed)


def quiet(cfg) -> bool:
    """No progress said at all: only when asked for (progress=false). On a terminal progress
    is a bar; elsewhere (a log file, CI) a plain line at most every 15 s, so no long stage is
    silent (`sagonline.core.progress`)."""
    return not cfg.progress


def settings_from(cfg) -> PipelineSettings:
    """What the pipeline takes from an EvalConfig (its groups are the pipeline's own)."""
    return PipelineSettings(
        cfg.renderer,
        cfg.label_render,
        cfg.metrics,
        device=cfg.device,
        progress=not quiet(cfg),
        feedback=cfg.feedback,
        diagnose=cfg.diagnose,
    )


def refine_config_from(cfg) -> RefineConfig | None:
    """The student's settings when Stage II runs (None otherwise), its `refine.pretrained` file
    opened (weights_only) before any work: a problem stops with the key's name."""
    if not cfg.refine.enabled:
        return None
    refine = cfg.refine  # a RefineStage is the student's RefineConfig, plus `enabled`
    if refine.pretrained:
        from sagonline.refine.network import ResNetEncoder, load_imagenet_weights

        try:
            load_imagenet_weights(ResNetEncoder(refine.encoder), refine.pretrained)
        except (ValueError, RuntimeError, OSError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
    return refine


def set_threads(cfg) -> int:
    """Threads for this job's torch ops and compiled kernels: `threads`, else the cores a
    submitit job was given (hydra.launcher.cpus_per_task), else the machine's cores divided
    among the jobs joblib runs at once (hydra.launcher.n_jobs), so parallel jobs do not
    oversubscribe the cores."""
    threads = cfg.threads
    if not threads:
        from hydra.core.hydra_config import HydraConfig

        try:
            launcher = HydraConfig.get().launcher
        except ValueError:  # composed directly (tests): no Hydra job
            return torch.get_num_threads()
        jobs = int(launcher.get("n_jobs") or 1)  # joblib: jobs at once on this machine
        threads = launcher.get("cpus_per_task")  # submitit: the job's own cores
        if not threads and jobs <= 1:
            return torch.get_num_threads()
        threads = threads or max(1, (os.cpu_count() or 1) // jobs)
    torch.set_num_threads(int(threads))
    return int(threads)


def check_device(device: str, backends=None) -> None:
    """Stop before any work when the requested device does not exist here, or when a backend
    (the renderer group's `backend` and `vote_backend`) cannot run on it or is not installed."""
    from sagonline.core.machine import check_device as check
    from sagonline.render.backends import BackendError, plan_backends

    try:
        check(device)
    except ValueError as exc:
        print(f"error: device={device}: {str(exc).split(': ', 1)[-1]}", file=sys.stderr)
        raise SystemExit(2) from None
    if backends is not None:
        try:
            plan_backends(backends.backend, backends.vote_backend, device)
        except BackendError as exc:
            print(f"error: renderer: {exc}", file=sys.stderr)
            raise SystemExit(2) from None


def build_dataset(node: dict):
    """The dataset's adapter, built from the registry by `node['kind']` with the node's
    `adapter` settings; a problem stops with one line naming the key."""
    from sagonline.core.errors import DatasetError
    from sagonline.core.plugins import DATASETS, PluginError

    try:
        return DATASETS.build(node.get("kind"), node.get("adapter") or {}, where="dataset.adapter")
    except (PluginError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def check_jobs(ap, jobs: int) -> None:
    """--jobs: processes at once, each on one thread: 1 to this machine's cores."""
    cores = os.cpu_count() or 1
    if not 1 <= jobs <= cores:
        ap.error(f"--jobs {jobs}: 1 to {cores} (this machine's cores; each job runs one thread)")
