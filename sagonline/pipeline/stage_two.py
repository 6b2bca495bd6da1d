"""Stage II: the refinement student trains in the background while the initial mode answers.

The student's checkpoint is keyed like a cached stage (`stages.REFINE`: the frames, masks and
vote it learns from and its settings), so an interrupted training resumes and a finished one is
reused. While it trains, the initial mode (fused labels rendered) keeps answering the eval
views; once it has converged or spent its budget, the eval views are answered again in refined
mode and both modes are scored.
"""

from __future__ import annotations

import logging
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from sagonline.datasets.base import SceneTask
from sagonline.pipeline.scene import PipelineSettings, StageOneOutput, nearest_frames
from sagonline.pipeline.scoring import SceneReport, record_scores
from sagonline.pipeline.stages import REFINE, RefineInputs
from sagonline.recording import Recorder
from sagonline.refine import RefineConfig, RefinementTrainer
from sagonline.refine.service import OnlineSegmentation
from sagonline.render.api import resolve_backend


def student_checkpoint(
    cache_dir: Path | None, stage_one: StageOneOutput, cfg: RefineConfig, settings
) -> Path | None:
    """Where the student's checkpoint for these inputs lives (None: no cache)."""
    if cache_dir is None:
        return None
    backend = resolve_backend(settings.backend, settings.device)
    inputs = RefineInputs(
        stage_one.frames, stage_one.masks, stage_one.vote, cfg, backend, str(settings.device)
    )
    return Path(cache_dir) / f"{REFINE.name}-{REFINE.key(inputs)}.store"


def answer_while_training(service: OnlineSegmentation, trainer: RefinementTrainer, views) -> list:
    """Answer the views in initial mode until the trainer is done (at least one full pass, so a
    student resumed from a finished checkpoint is still timed); ms of each initial answer."""
    initial = []
    while not (trainer.done.is_set() and len(initial) >= len(views)):
        for view in views:
            answer = service.answer(view.camera, "initial")
            initial.append(answer.ms)
            if trainer.done.is_set() and len(initial) >= len(views):
                break
    return initial


def say_why_it_stopped(scene: str, trainer: RefinementTrainer, cfg: RefineConfig) -> None:
    """On screen (and in the run's log): why the student stopped, and a warning when a time
    budget stopped it."""
    why = {
        "converged": f"converged (no gain of {cfg.min_delta} in {cfg.patience} steps)",
        "steps": f"its step budget (refine.max_steps={cfg.max_steps})",
        "time_budget": f"its time budget (refine.time_budget_s={cfg.time_budget_s})",
    }.get(trainer.status, trainer.status)
    line = f"{scene}: the student stopped at step {trainer.step} ({trainer.train_s:.1f} s): {why}"
    if trainer.status == "time_budget":
        warnings.warn(
            f"{line}; its answers depend on how busy the machine was (drop "
            "refine.time_budget_s to bound it by steps)",
            stacklevel=2,
        )
    print(line, file=sys.stderr)
    logging.getLogger("sagonline.refine").info(line)


def run_stage_two(
    task: SceneTask,
    stage_one: StageOneOutput,
    cfg: RefineConfig,
    settings: PipelineSettings,
    report: SceneReport,
    recorder: Recorder,
    checkpoint: str | Path | None = None,
    predictions_to: str | Path | None = None,
) -> None:
    """Train the student in the background while the initial mode keeps answering the eval
    views, then answer them again in refined mode; both are scored into `report`."""
    vote = stage_one.vote.value
    service = OnlineSegmentation(
        task.gaussians.to(settings.device),
        vote.labels,
        vote.labelled,
        stage_one.num_labels,
        backend=settings.backend,
        min_weight=settings.label_min_weight,
    )
    coarse = [service.coarse(c) for c in task.trajectory]
    trainer = RefinementTrainer(
        cfg,
        stage_one.num_labels,
        stage_one.frames.value.images,
        coarse,
        stage_one.masks.value.masks,
        checkpoint,
    )
    service.trainer = trainer
    start = time.perf_counter()
    resumed_done = trainer.done.is_set()
    trainer.start()
    initial = answer_while_training(service, trainer, task.eval_views)
    trainer.wait()
    switched = time.perf_counter() - start
    say_why_it_stopped(task.name, trainer, cfg)
    answers = [service.answer(v.camera, "refined") for v in task.eval_views]
    preds = [a.mask for a in answers]
    report.refined_miou, report.refined_macc = record_scores(
        task, preds, settings.resize, report, "refined", stage_one.voted, predictions_to
    )
    report.timings.update(
        {
            "initial_ms_per_frame": float(np.mean(initial)),
            "refined_ms_per_frame": float(np.mean([a.ms for a in answers])),
            "refine_train_s": trainer.train_s,
            "refine_switch_s": switched,
        }
    )
    report.extra["refine"] = {
        "status": trainer.status,
        "steps": trainer.step,
        "final_loss": trainer.ema,
        "resumed_finished": resumed_done,
        "initial_answers_while_training": len(initial),
        "encoder": cfg.encoder,
    }
    if recorder.enabled:
        ious = [r["iou"] for r in report.views[-len(preds) :]] if preds else []
        frames = nearest_frames(task)
        for i, pred in enumerate(preds):
            recorder.refined_view(task.name, i, pred, iou=ious[i], frame=frames[i])
