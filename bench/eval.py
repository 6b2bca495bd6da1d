"""Stage I evaluation: `python -m bench.eval dataset=synthetic segmenter=oracle consensus=rgc`.

Writes metrics.json, per_view.csv and recording.rrd into the Hydra run directory.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig

from bench.common import (
    build_plugin,
    guard_run_dir,
    plugin_kwargs,
    print_summary,
    refine_config_from,
    seed_everything,
    settings_from,
    vote_config_from,
    write_outputs,
)
from sagonline.datasets.base import DatasetError
from sagonline.pipeline import (
    SceneReport,
    run_stage_one,
    run_stage_two,
    settings_key,
    summarize,
)
from sagonline.recording import Recorder


def evaluate(cfg: DictConfig, out_dir: Path) -> dict:
    guard_run_dir(out_dir, cfg.overwrite)
    seed_everything(cfg.seed)
    try:
        adapter = instantiate(cfg.dataset.adapter)
        scenes = adapter.scene_names()
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    segmenter = build_plugin(cfg.segmenter, "segmenter")
    vote_cfg = vote_config_from(cfg)
    settings = settings_from(cfg)
    recorder = Recorder(out_dir / "recording.rrd" if cfg.record else None)
    cache_root = Path(cfg.cache_dir) if cfg.get("cache_dir") else out_dir / "cache"
    refine_key = settings_key(
        *(str(cfg[k]) for k in ("dataset", "segmenter", "consensus", "refine", "label_render"))
    )
    reports: list[SceneReport] = []
    try:
        for scene in scenes:
            try:
                task = adapter.load_scene(scene)
            except DatasetError as exc:
                print(f"warning: scene {scene} skipped: {exc}", file=sys.stderr)
                reports.append(SceneReport(scene=scene, status="failed", error=str(exc)))
                continue
            report, vote, artefacts = run_stage_one(
                task,
                segmenter,
                vote_cfg,
                settings,
                segmenter_key=plugin_kwargs(cfg.segmenter) | {"name": cfg.segmenter.name},
                cache_dir=cache_root / scene if cfg.cache else None,
                recorder=recorder,
            )
            if cfg.refine.enabled:
                run_stage_two(
                    task,
                    vote,
                    artefacts,
                    refine_config_from(cfg),
                    settings,
                    report,
                    recorder,
                    checkpoint=cache_root / scene / f"refine-{refine_key}.pt"
                    if cfg.cache
                    else None,
                )
            reports.append(report)
    finally:
        recorder.close()
    metrics = write_outputs(
        out_dir,
        cfg,
        reports,
        summarize(reports),
        {"protocol": adapter.describe(), "config_key": settings_key(str(cfg))},
    )
    print_summary(out_dir, metrics, reports)
    return metrics


def overrides() -> list[str]:
    """The command-line overrides of this job (what distinguishes it inside a sweep)."""
    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:  # not running under @hydra.main (tests compose the config directly)
        return []


@hydra.main(version_base="1.3", config_path="../conf", config_name="eval")
def main(cfg: DictConfig) -> None:
    evaluate(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
