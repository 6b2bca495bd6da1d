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
    return not cfg.progress or os.environ.get("CI", "").lower() in ("1", "true")


def settings_from(cfg) -> PipelineSettings:
    """What the pipeline takes from an EvalConfig."""
    return PipelineSettings(
        backend=cfg.renderer.backend,
        device=cfg.device,
        label_min_weight=cfg.label_render.min_weight,
        resize=cfg.metrics.resize,
        progress=not quiet(cfg),
        feedback=cfg.feedback,
    )


def refine_config_from(cfg) -> RefineConfig | None:
    """The student's settings when Stage II runs (None otherwise), its `refine.pretrained` file
    opened (weights_only) before any work: a problem stops with the key's name."""
    if not cfg.refine.enabled:
        return None
    fields = {k: v for k, v in vars(cfg.refine).items() if k != "enabled"}
    refine = RefineConfig(**fields)
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


def check_device(device: str) -> None:
    """Stop before any work when the requested device does not exist here."""
    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        print(f"error: device={device}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(
            f"error: device={device}: CUDA is not available here (torch {torch.__version__}); "
            "use device=cpu",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        print(
            f"error: device={device}: only {torch.cuda.device_count()} CUDA device(s) here",
            file=sys.stderr,
        )
        raise SystemExit(2)


def build_plugin(node: dict, what: str):
    """Instantiate a plug-in from its config node (`_target_` and arguments); a configuration
    problem stops with its own message, not a trace."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate(plugin_kwargs(node))
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        print(f"error: {what} {node.get('name', '')}: {cause}", file=sys.stderr)
        raise SystemExit(2) from None


def plugin_kwargs(node: dict) -> dict:
    """A plug-in's config without the keys that are ours, not its constructor's."""
    return {k: v for k, v in node.items() if k != "name"}
