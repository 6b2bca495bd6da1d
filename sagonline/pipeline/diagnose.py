"""Stage I's diagnosis of a scored scene (`score.diagnosis`): every eval view's wrong pixels
sorted by cause, in per_view.csv (the view's row), in metrics.json (the scene's shares) and in
the recording (a colour image of the causes beside the prediction).

The split between the fit and the segmenter needs the vote the truth's own masks would give on
the same views by the same rule: for a dataset with the trajectory's ground truth, that vote is
Stage I run with the oracle segmenter (cached like any stage; for an oracle run it is the run's
own vote)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from sagonline.datasets.base import SceneTask
from sagonline.pipeline.graph import StageCache
from sagonline.pipeline.scoring import SceneReport
from sagonline.pipeline.settings import PipelineSettings
from sagonline.pipeline.stage_one import StageOneOutput, compose_stage_one
from sagonline.pipeline.stages import SegmenterRun, segmenter_run
from sagonline.scene.gaussians import Gaussians
from sagonline.score.alignment import SHIFT_KEYS, displaced
from sagonline.score.diagnosis import (
    GaussianCauses,
    OutsideTally,
    cause_image,
    diagnose_view,
    outside_summary,
    shares,
)
from sagonline.vote.consensus import VoteConfig, VoteResult


def truth_vote(
    task: SceneTask,
    gaussians: Gaussians,
    stage_one: StageOneOutput,
    segmenter: SegmenterRun,
    vote: VoteConfig,
    settings: PipelineSettings,
    cache: StageCache,
) -> VoteResult | None:
    """The vote of the trajectory's ground-truth masks on the run's voting views, by the run's
    rule; None without that ground truth."""
    if task.trajectory_gt is None:
        return None
    from sagonline.segment.oracle import OracleSegmenter

    own = segmenter.segmenter
    if type(own) is OracleSegmenter and not own.corruption.active:  # the run's masks are the truth
        return stage_one.vote.value
    oracle = segmenter_run({"kind": "oracle"}, check=False)
    quiet = replace(settings, progress=False)
    truth = compose_stage_one(
        gaussians,
        task.trajectory,
        task.prompt,
        oracle,
        vote,
        quiet,
        num_labels=task.num_labels,
        trajectory_gt=task.trajectory_gt,
        cache=cache,
    )
    return truth.vote.value


def diagnose_scene(
    task: SceneTask,
    gaussians: Gaussians,
    stage_one: StageOneOutput,
    preds: list[np.ndarray],
    segmenter: SegmenterRun,
    vote: VoteConfig,
    settings: PipelineSettings,
    report: SceneReport,
    cache: StageCache,
) -> list[np.ndarray]:
    """Add each eval view's cause counts to its per-view row, the scene's shares to
    report.extra["diagnosis"] (with the views whose object is rendered displaced,
    `score.alignment`) and the labelled Gaussians shown outside the object's silhouette to
    report.outside (their summary under diagnosis["outside"]); returns the (H, W, 3) cause
    images (for the recording)."""
    truth = truth_vote(task, gaussians, stage_one, segmenter, vote, settings, cache)
    causes = GaussianCauses.of(stage_one.vote.value, vote, truth)
    rows = {(r["view"], r["mode"]): r for r in report.views}
    counts, images, outside = [], [], OutsideTally()
    for view, pred in zip(task.eval_views, preds, strict=True):
        row = rows[(view.name, "coarse")]
        c, kinds = diagnose_view(
            gaussians,
            view.camera,
            view.gt,
            pred,
            causes,
            ignore=task.ignore_label,
            backend=settings.renderer.backend,
            outside=outside,
            voted=bool(row.get("voted")),
        )
        row.update(c)
        counts.append(c)
        images.append(cause_image(kinds))
    report.outside = outside.rows(gaussians, causes)
    report.extra["diagnosis"] = shares(counts) | {
        "counterfactual": "truth's masks" if truth is not None else None,
        "outside": outside_summary(report.outside, sum(c["extra_px"] for c in counts)),
        "displaced": [
            {"view": view.name, **{k: c[k] for k in SHIFT_KEYS}}
            for view, c in zip(task.eval_views, counts, strict=True)
            if displaced(c, view.camera.width, view.camera.height)
        ],
    }
    return images
