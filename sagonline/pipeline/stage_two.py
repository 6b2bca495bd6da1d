"""Stage II: the refinement student trains in the background while the other modes answer.

The student's checkpoint is keyed like a cached stage (`stages.REFINE`: the frames, masks and
vote it learns from and its settings), so an interrupted training resumes and a finished one is
reused. While it trains, the eval views are answered in every mode in turn (coarse: the fused
labels rendered; initial: the 2D segmenter on the view's render; refined: the student as it is
then), each answer timed; once it has converged or spent its budget, they are answered again in
each mode alone (the paper's Table II, `sagonline.refine.service`) and the refined answers
are scored.
"""

from __future__ import annotations

import logging
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sagonline.datasets.base import SceneTask
from sagonline.pipeline.scene import nearest_frames, task_settings
from sagonline.pipeline.scoring import SceneReport, mean_iou, record_scores
from sagonline.pipeline.settings import PipelineSettings
from sagonline.pipeline.stage_one import StageOneOutput
from sagonline.pipeline.stages import REFINE, RefineInputs, SegmenterRun
from sagonline.record.recording import Recorder
from sagonline.refine import RefineConfig, RefinementTrainer
from sagonline.refine.service import OnlineSegmentation
from sagonline.render.api import resolve_backend
from sagonline.segment.novel_view import NovelViewSegmenter


def student_checkpoint(
    cache_dir: Path | None, stage_one: StageOneOutput, cfg: RefineConfig, settings
) -> Path | None:
    """Where the student's checkpoint for these inputs lives (None: no cache)."""
    if cache_dir is None:
        return None
    backend = resolve_backend(settings.renderer.backend, settings.device)
    inputs = RefineInputs(
        stage_one.frames, stage_one.masks, stage_one.vote, cfg, backend, str(settings.device)
    )
    return Path(cache_dir) / f"{REFINE.name}-{REFINE.key(inputs)}.store"


def answer_while_training(
    service: OnlineSegmentation, trainer: RefinementTrainer, views, modes: list[str]
) -> dict[str, list[float]]:
    """Answer the views in each of `modes` in turn until the trainer is done (at least one full
    pass); mode -> ms of each answer. The refined answers come from the student as it is."""
    ms: dict[str, list[float]] = {mode: [] for mode in modes}
    while not (trainer.done.is_set() and len(ms[modes[-1]]) >= len(views)):
        for view in views:
            for mode in modes:
                ms[mode].append(service.answer(view.camera, mode, view.gt).ms)
            if trainer.done.is_set() and len(ms[modes[-1]]) >= len(views):
                break
    return ms


def answer_alone(service: OnlineSegmentation, views, mode: str, settings: PipelineSettings) -> list:
    """Each view's answer in `mode`, nothing else running in the process; the student's at the
    size the coarse labels are scored at (`label_render.size`)."""
    answers = []
    for view in views:
        scored = settings.scored_camera(view)
        size = (scored.height, scored.width) if mode == "refined" else None
        answers.append(service.answer(view.camera, mode, view.gt, size))
    return answers


def curve_scorer(
    task: SceneTask, service: OnlineSegmentation, trainer: RefinementTrainer, settings
) -> Callable[[bool], float | None]:
    """The student's mIoU at the eval views as it is when called (`refine.curve_every`,
    `refine.scored_spans`): their RGB and coarse renders made once here, answered at the size
    the refined answers are scored at, scored as they are; its answers', or those of the
    weights `span` names (`RefinementTrainer.predict`)."""
    inputs = []
    for view in task.eval_views:
        scored = settings.scored_camera(view)
        inputs.append((service.rgb(view.camera), service.coarse(view.camera), scored))
    truths = [view.gt for view in task.eval_views]

    def score_now(span: int | None = None) -> float | None:
        preds = [
            trainer.predict(rgb, coarse, (c.height, c.width), span) for rgb, coarse, c in inputs
        ]
        return mean_iou(task, preds, truths, settings.metrics.resize)

    return score_now


def say_why_it_stopped(scene: str, trainer: RefinementTrainer, cfg: RefineConfig) -> None:
    """On screen (and in the run's log): why the student stopped, and a warning when a time
    budget stopped it."""
    why = {
        "converged": (
            f"converged (no gain of {cfg.min_delta} in the smoothed loss for {cfg.patience} "
            f"steps after a warm-up of {cfg.patience}; lowest at step "
            f"{trainer.plateau.best_step})"
        ),
        "steps": f"its step budget (refine.max_steps={cfg.max_steps})",
        "time_budget": f"its time budget (refine.time_budget_s={cfg.time_budget_s})",
    }.get(trainer.status, trainer.status)
    line = f"{scene}: the student stopped at step {trainer.step} ({trainer.train_s:.1f} s): {why}"
    if trainer.average is not None:
        line += f"; it answers from the average of its weights over about {cfg.ema_span} steps"
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
    segmenter: SegmenterRun | None = None,
) -> None:
    """Train the student in the background while the eval views are answered in every mode
    (initial only with a `segmenter`: the run's), then answer them in each mode alone; the
    refined
    answers are scored into `report`, the timings of every mode go into `report.timings`.

    Why one function: it is the Stage II timeline (start, answer while training, switch,
    answer alone), whose order the timings depend on."""
    settings = task_settings(task, settings)  # its renders on the colour Stage I's were
    vote = stage_one.vote.value
    novel = None
    if segmenter is not None:
        novel = NovelViewSegmenter(
            segmenter.segmenter,
            stage_one.frames.value.images,
            stage_one.masks.value.masks,
            task.trajectory,
            task.prompt,
            task.trajectory_gt,
        )
    service = OnlineSegmentation(
        task.gaussians.to(settings.device),
        vote.labels,
        stage_one.num_labels,
        segmenter=novel,
        backend=settings.renderer.backend,
        min_weight=settings.label_render.min_weight,
        background=settings.background,
    )
    modes = ["coarse", "initial", "refined"] if novel is not None else ["coarse", "refined"]
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
    if cfg.curve_every:
        trainer.score_now = curve_scorer(task, service, trainer, settings)
    start = time.perf_counter()
    resumed_done = trainer.done.is_set()
    trainer.start()
    during = answer_while_training(service, trainer, task.eval_views, modes)
    trainer.wait()
    switched = time.perf_counter() - start
    say_why_it_stopped(task.name, trainer, cfg)
    alone = {mode: answer_alone(service, task.eval_views, mode, settings) for mode in modes}
    preds = [a.mask for a in alone["refined"]]
    report.refined_miou, report.refined_macc = record_scores(
        task, preds, settings.metrics.resize, report, "refined", stage_one.voted, predictions_to
    )
    for mode in modes:
        report.timings[f"{mode}_ms_per_frame"] = float(np.mean([a.ms for a in alone[mode]]))
        if not resumed_done:  # a student resumed finished trained beside none of them
            report.timings[f"{mode}_ms_per_frame_training"] = float(np.mean(during[mode]))
    report.timings.update({"refine_train_s": trainer.train_s, "refine_switch_s": switched})
    report.extra["refine"] = {
        "status": trainer.status,
        "steps": trainer.step,
        "final_loss": trainer.plateau.ema,
        "best_step": trainer.plateau.best_step,
        "resumed_finished": resumed_done,
        "answers_while_training": {mode: len(v) for mode, v in during.items()},
        "encoder": cfg.encoder,
        "ema_span": cfg.ema_span,
    }
    if cfg.curve_every:
        report.extra["refine"]["curve"] = trainer.curve
    if cfg.scored_spans:  # by span, 0: the trained weights
        score = trainer.score_now or curve_scorer(task, service, trainer, settings)
        spans = sorted({0, cfg.ema_span, *cfg.scored_spans})
        report.extra["refine"]["span_miou"] = {str(span): score(span) for span in spans}
    if novel is not None:
        initial = [a.mask for a in alone["initial"]]
        truths = [v.gt for v in task.eval_views]
        report.extra["initial_mode_miou"] = mean_iou(task, initial, truths, settings.metrics.resize)
    if recorder.enabled:
        ious = [r["iou"] for r in report.views[-len(preds) :]] if preds else []
        frames = nearest_frames(task)
        for i, pred in enumerate(preds):
            recorder.refined_view(task.name, i, pred, iou=ious[i], frame=frames[i])
