"""A dataset's scenes evaluated: Stage I on each (and Stage II where a refinement config is
given), scored against the dataset's protocol. A scene that cannot load or be scored is
reported as failed and the others go on. The front end (`python -m bench.runners.eval`) adds
the run folder around it: its config, lock, log, metrics.json and summary."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from sagonline.datasets.base import DatasetAdapter, DatasetError
from sagonline.pipeline.scene import run_scene
from sagonline.pipeline.scoring import SceneReport
from sagonline.pipeline.settings import PipelineSettings
from sagonline.pipeline.stage_two import run_stage_two, student_checkpoint
from sagonline.pipeline.stages import SegmenterRun
from sagonline.record.recording import Recorder
from sagonline.refine import RefineConfig
from sagonline.vote.consensus import VoteConfig

log = logging.getLogger("sagonline.eval")
# `extra=` of log records meant for the run's log file, not the console
FILE_ONLY = {"file_only": True}


def evaluate_scenes(
    adapter: DatasetAdapter,
    scenes: list[str],
    segmenter: SegmenterRun,
    vote: VoteConfig,
    settings: PipelineSettings,
    *,
    refine: RefineConfig | None = None,
    cache_root: Path | None = None,
    recording: Path | None = None,
    predictions_to: Path | None = None,
    warn: Callable[[str], None] = log.warning,
) -> list[SceneReport]:
    """One `SceneReport` per scene of `scenes`, in order: Stage I on the scene's views with
    `segmenter`'s masks and the `vote`, scored; with `refine`, Stage II's student trained and
    scored too. `cache_root`: the stage cache (one folder per scene; None: nothing cached);
    `recording`: the rerun recording's file (None: none); `predictions_to`: the run folder
    that receives the scored label maps. A scene that fails to load is said through `warn`
    and reported as failed."""
    recorder = Recorder(recording, scenes=list(scenes), refined=refine is not None)
    reports: list[SceneReport] = []
    try:
        for scene in scenes:
            cache = cache_root / scene if cache_root is not None else None
            try:
                task = adapter.load_scene(scene)
                report, stage_one = run_scene(
                    task,
                    segmenter,
                    vote,
                    settings,
                    cache_dir=cache,
                    recorder=recorder,
                    predictions_to=predictions_to,
                )
            except DatasetError as exc:
                warn(f"scene {scene} skipped: {exc}")
                failed = SceneReport(scene, status="failed", error=str(exc))
                failed.protocol = adapter.protocol
                reports.append(failed)
                continue
            report.protocol = adapter.protocol
            if refine is not None:
                checkpoint = student_checkpoint(cache, stage_one, refine, settings)
                run_stage_two(
                    task,
                    stage_one,
                    refine,
                    settings,
                    report,
                    recorder,
                    checkpoint,
                    predictions_to,
                    segmenter,
                )
            log.info("scene %s: stages %s", scene, report.stages, extra=FILE_ONLY)
            reports.append(report)
    finally:
        recorder.close()
    return reports
