"""Shared by the entry points: run-directory guard, config plumbing, output writers."""

from __future__ import annotations

import os
import random
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from sagonline.consensus import VoteConfig
from sagonline.pipeline import PipelineSettings, SceneReport
from sagonline.utils import atomic_write_json, atomic_write_text, describe_device


class RunExists(SystemExit):
    pass


def guard_run_dir(out_dir: Path, overwrite: bool) -> None:
    """Never overwrite a finished run silently."""
    if (out_dir / "metrics.json").exists() and not overwrite:
        print(
            f"error: {out_dir} already holds a finished run (metrics.json). Choose another "
            "hydra.run.dir, or pass overwrite=true to replace it.",
            file=sys.stderr,
        )
        raise RunExists(2)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (legacy global RNG some plug-ins still use)
    torch.manual_seed(seed)


def quiet(cfg: DictConfig) -> bool:
    return not cfg.get("progress", True) or os.environ.get("CI", "").lower() in ("1", "true")


def settings_from(cfg: DictConfig) -> PipelineSettings:
    return PipelineSettings(
        backend=cfg.renderer.backend,
        device=cfg.device,
        label_min_weight=cfg.label_render.min_weight,
        resize=cfg.metrics.resize,
        progress=not quiet(cfg),
    )


def refine_config_from(cfg: DictConfig):
    from sagonline.refine import RefineConfig

    d = OmegaConf.to_container(cfg.refine, resolve=True)
    d.pop("enabled", None)
    return RefineConfig(**d)


def vote_config_from(cfg: DictConfig) -> VoteConfig:
    return VoteConfig(**OmegaConf.to_container(cfg.consensus, resolve=True))


def build_plugin(node: DictConfig, what: str):
    """Instantiate a plug-in; a configuration problem stops with its own message, not a trace."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate(plugin_kwargs(node))
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        print(f"error: {what} {node.get('name', '')}: {cause}", file=sys.stderr)
        raise SystemExit(2) from None


def plugin_kwargs(node: DictConfig) -> dict:
    """A plug-in's config without the keys that are ours, not its constructor's."""
    d = OmegaConf.to_container(node, resolve=True)
    d.pop("name", None)
    return d


def write_outputs(
    out_dir: Path,
    cfg: DictConfig,
    reports: list[SceneReport],
    summary: dict,
    extra: dict | None = None,
) -> dict:
    """metrics.json (+ per_view.csv) atomically into the run directory."""
    from sagonline.metrics import RESIZE_RULES

    metrics = {
        "dataset": cfg.dataset.name,
        "segmenter": cfg.segmenter.get("name", "segmenter"),
        "consensus": OmegaConf.to_container(cfg.consensus, resolve=True),
        "renderer": cfg.renderer.backend,
        **summary,
        "resize_rule": RESIZE_RULES[cfg.metrics.resize],
        "device": describe_device(cfg.device),
        "scenes": [{k: v for k, v in asdict(r).items() if k != "views"} for r in reports],
        "config": OmegaConf.to_container(cfg, resolve=True),
        **(extra or {}),
    }
    rows = [v for r in reports for v in r.views]
    atomic_write_text(
        out_dir / "per_view.csv",
        pd.DataFrame(rows, columns=["scene", "view", "mode", "iou", "acc"]).to_csv(index=False),
    )
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def fmt(x, pct: bool = True) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.2f}" if pct else f"{x:.1f}"


def print_summary(out_dir: Path, metrics: dict, reports: list[SceneReport]) -> None:
    """One screen: per-scene rows, overall numbers, where the outputs are."""
    lines = [
        f"dataset {metrics['dataset']}  segmenter {metrics['segmenter']}  "
        f"consensus {metrics['consensus']['method']}  renderer {metrics['renderer']}",
        "",
    ]
    lines.append(
        f"{'scene':<22}{'status':<9}{'mIoU':>8}{'mAcc':>8}{'seg mIoU':>10}"
        f"{'3D acc':>8}{'3D cov':>8}{'vote ms/mask':>14}{'refined':>9}"
    )
    for r in reports:
        l3 = r.labels3d or {}
        lines.append(
            f"{r.scene:<22}{r.status:<9}{fmt(r.miou):>8}{fmt(r.macc):>8}"
            f"{fmt(r.segmenter_miou):>10}{fmt(l3.get('accuracy')):>8}"
            f"{fmt(l3.get('coverage')):>8}"
            f"{fmt(r.timings.get('vote_ms_per_mask'), False):>14}{fmt(r.refined_miou):>9}"
        )
        if r.error:
            lines.append(f"    {r.error}")
    lines += [
        "",
        f"overall mIoU {fmt(metrics['miou'])}  mAcc {fmt(metrics['macc'])}  "
        f"segmenter mIoU {fmt(metrics['segmenter_miou'])}"
        + (f"  refined mIoU {fmt(metrics['refined_miou'])}" if metrics.get("refined_miou") else "")
        + ("   (PARTIAL: some scenes failed)" if metrics.get("partial") else ""),
        f"resize rule: {metrics['resize_rule']}",
        f"outputs: {out_dir}/metrics.json, per_view.csv"
        + (
            ", recording.rrd (open with: rerun recording.rrd)"
            if (out_dir / "recording.rrd").exists()
            else ""
        ),
    ]
    print("\n".join(lines))
