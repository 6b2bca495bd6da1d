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

from sagonline.datasets.base import EvalView, SceneTask
from sagonline.pipeline.graph import StageCache
from sagonline.pipeline.scoring import SceneReport
from sagonline.pipeline.settings import PipelineSettings
from sagonline.pipeline.stage_one import StageOneOutput, compose_stage_one
from sagonline.pipeline.stages import SegmenterRun, segmenter_run
from sagonline.render.rasterize import RenderOutput
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
        rendered=stage_one.frames,  # the run's frames: never rendered twice
    )
    return truth.vote.value


class SceneDiagnosis:
    """A scored scene's diagnosis, one eval view at a time (`view`), then `finish`: each view's
    cause counts in its per-view row, the scene's shares in report.extra["diagnosis"] (with the
    views whose object is rendered displaced, `score.alignment`) and the labelled Gaussians
    shown outside the object's silhouette in report.outside (their summary under
    diagnosis["outside"])."""

    def __init__(
        self,
        task: SceneTask,
        gaussians: Gaussians,
        stage_one: StageOneOutput,
        segmenter: SegmenterRun,
        vote: VoteConfig,
        settings: PipelineSettings,
        report: SceneReport,
        cache: StageCache,
    ) -> None:
        truth = truth_vote(task, gaussians, stage_one, segmenter, vote, settings, cache)
        self.causes = GaussianCauses.of(stage_one.vote.value, vote, truth)
        self.task, self.gaussians, self.report = task, gaussians, report
        self.backend = settings.renderer.backend
        self.rows = {(r["view"], r["mode"]): r for r in report.views}
        self.counts: list[dict] = []
        self.outside = OutsideTally()

    def view(
        self, view: EvalView, pred: np.ndarray, whole: RenderOutput | None = None
    ) -> np.ndarray:  # [H, W, 3] uint8
        """Diagnose the next eval view (pred: its coarse label render; whole: the scene's
        render there with ids, if the caller has it); returns its cause image."""
        row = self.rows[(view.name, "coarse")]
        counts, kinds = diagnose_view(
            self.gaussians,
            view.camera,
            view.gt,
            pred,
            self.causes,
            ignore=self.task.ignore_label,
            backend=self.backend,
            outside=self.outside,
            voted=bool(row.get("voted")),
            whole=whole,
        )
        row.update(counts)
        self.counts.append(counts)
        return cause_image(kinds)

    def finish(self) -> None:
        """Write the scene's shares and the Gaussians shown outside into the report."""
        counts, views = self.counts, self.task.eval_views
        if len(counts) != len(views):
            raise RuntimeError(f"diagnosed {len(counts)} of {len(views)} eval views")
        report = self.report
        report.outside = self.outside.rows(self.gaussians, self.causes)
        report.extra["diagnosis"] = shares(counts) | {
            "counterfactual": "truth's masks" if self.causes.truth is not None else None,
            "outside": outside_summary(report.outside, sum(c["extra_px"] for c in counts)),
            "displaced": [
                {"view": view.name, **{k: c[k] for k in SHIFT_KEYS}}
                for view, c in zip(views, counts, strict=True)
                if displaced(c, view.camera.width, view.camera.height)
            ],
        }
