"""Scoring: what a scene's numbers are, and the dataset-level summary.

A `SceneReport` holds everything measured on one scene. Views are scored one row each (IoU and
accuracy against the ground truth, whether the view's mask voted, and the view's own metadata
from the dataset); where a dataset sorts its eval views into groups (`EvalView.group`, e.g. a
capture photographed for some views only: "photographed" / "mask_only"), each group's mIoU is
reported beside the scene's.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sagonline.core.errors import DatasetError
from sagonline.datasets.base import SceneTask
from sagonline.score.metrics import match_and_relabel, view_metrics
from sagonline.score.predictions import folder_sha256, view_file, write_label_map


@dataclass
class SceneReport:
    """Everything measured on one scene; `views` are per-view metric rows."""

    scene: str
    status: str = "ok"
    miou: float | None = None
    macc: float | None = None
    segmenter_miou: float | None = None
    labels3d: dict | None = None
    vote: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    views: list[dict] = field(default_factory=list)
    error: str | None = None
    refined_miou: float | None = None
    refined_macc: float | None = None
    extra: dict = field(default_factory=dict)
    stages: dict = field(default_factory=dict)  # stage -> "computed" | "cached"
    cached_timings: dict = field(default_factory=dict)  # timings of the run that built a cache
    inputs: dict = field(default_factory=dict)  # content digests of what this scene consumed
    stage_keys: dict = field(default_factory=dict)  # stage -> its cache key (`sagonline export`)
    protocol: str | None = None  # the evaluation protocol's id, e.g. nvos/scribbles-skeleton@1
    outside: list[dict] = field(default_factory=list)  # labelled Gaussians shown outside the
    # object's silhouette (`score.diagnosis.OutsideTally.rows`): gaussians_outside.csv

    def add_timings(self, stages: tuple[str, ...], **times: float) -> None:
        """This run's timings when it computed every one of `stages`, else the cached run's
        (kept apart, under `cached_timings`)."""
        fresh = all(self.stages.get(s) == "computed" for s in stages)
        (self.timings if fresh else self.cached_timings).update(times)


def save_predictions(
    task: SceneTask, preds: list[np.ndarray], report: SceneReport, mode: str, run: Path
) -> None:
    """The scored label maps of `mode` (and, with the coarse mode, the ground truth) as PNGs
    under the run folder; their folders' SHA-256 into report.extra."""
    folder = run / ("predictions" if mode == "coarse" else f"predictions_{mode}")
    for view, pred in zip(task.eval_views, preds, strict=True):
        write_label_map(view_file(folder, task.name, view.name), pred)
    digests = report.extra.setdefault("sha256", {})
    digests[f"predictions_{mode}"] = folder_sha256(folder / task.name, "*.png")
    if mode == "coarse":
        truth = run / "ground_truth"
        for view in task.eval_views:
            write_label_map(view_file(truth, task.name, view.name), view.gt)
        digests["ground_truth"] = folder_sha256(truth / task.name, "*.png")
        report.extra["ignore_label"] = task.ignore_label


def check_ground_truth(task: SceneTask) -> list[str]:
    """Names of the scored views whose ground truth has no foreground (warned about). A scene
    whose every view is empty cannot be scored (every prediction but an empty one would score
    0, an empty one 100): it fails with a hint at the label format."""

    def has_foreground(gt: np.ndarray) -> bool:
        valid = gt if task.ignore_label is None else gt[gt != task.ignore_label]
        return bool((valid != 0).any())

    empty = [v.name for v in task.eval_views if not has_foreground(v.gt)]
    if task.eval_views and len(empty) == len(task.eval_views):
        raise DatasetError(
            f"{task.dataset}/{task.name}: none of the {len(empty)} ground-truth masks has any "
            "foreground; check the label format (0/1 masks read as `binary` need "
            "dataset.adapter.mask_threshold=0, or use label_format=ids)"
        )
    if empty:
        shown = ", ".join(empty[:5]) + (" ..." if len(empty) > 5 else "")
        warnings.warn(
            f"{task.dataset}/{task.name}: {len(empty)} of {len(task.eval_views)} ground-truth "
            f"masks have no foreground ({shown}); they score 100 only if the prediction is empty",
            stacklevel=2,
        )
    return empty


def is_automatic(task: SceneTask) -> bool:
    """No objects and no texts prompted: the segmenter's ids are arbitrary and get matched to
    the ground truth once per scene before scoring."""
    return not task.prompt.objects and not task.prompt.texts


def segmenter_miou(task: SceneTask, masks: list[np.ndarray], resize: str) -> float | None:
    """The 2D segmenter's own mIoU on the trajectory, where its ground truth is known."""
    if task.trajectory_gt is None:
        return None
    return mean_iou(task, masks, task.trajectory_gt, resize)


def mean_iou(task: SceneTask, preds: list[np.ndarray], truths: list[np.ndarray], resize: str):
    """Mean per-view IoU of (H, W) label maps against their ground truth (an automatic
    segmenter's ids matched to the truth's scene-wide first); None without views."""
    if not preds:
        return None
    if is_automatic(task):
        preds = match_and_relabel(preds, truths, resize, task.ignore_label)
    ious = [
        view_metrics(p, g, resize, task.ignore_label)["iou"]
        for p, g in zip(preds, truths, strict=True)
    ]
    return scored_mean(ious)


def scored_mean(values: list[float | None]) -> float | None:
    """The mean over the views that were scored (a view whose every pixel is ignored has
    None), or None when none was."""
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


def record_scores(
    task: SceneTask,
    preds: list[np.ndarray],
    resize: str,
    report: SceneReport,
    mode: str,
    voted: set[str] | None = None,
    save_to: Path | None = None,
) -> tuple[float | None, float | None]:
    """Per-view rows for `mode` ("coarse": the fused labels rendered, or "refined": the student)
    and their means; the coarse mode's
    means are the report's `miou`/`macc`. `voted`: names of the views whose masks voted.
    preds: one (H, W) label map per eval view (automatic ids are matched here). `save_to`: a
    run folder to write the scored label maps (and the ground truth) into, as PNGs with their
    SHA-256 in the report (`sagonline.score.predictions`)."""
    if is_automatic(task) and preds:
        preds = match_and_relabel(preds, [v.gt for v in task.eval_views], resize, task.ignore_label)
        report.extra["label_matching"] = "hungarian, scene-wide"
    if save_to is not None:
        save_predictions(task, preds, report, mode, Path(save_to))
    rows = []
    for view, pred in zip(task.eval_views, preds, strict=True):
        m = view_metrics(pred, view.gt, resize, task.ignore_label)
        rows.append(
            {
                "scene": task.name,
                "view": view.name,
                "mode": mode,
                "iou": m["iou"],
                "acc": m["acc"],
                "voted": view.name in (voted or ()),
                **view.meta,
            }
        )
        if m.get("skipped"):
            report.extra.setdefault("skipped_views", {})[view.name] = m["skipped"]
    if task.view_groups:
        split = report.extra.setdefault("by_view_group", {})
        for group in task.view_groups:
            ious = [
                r["iou"] for r, v in zip(rows, task.eval_views, strict=True) if v.group == group
            ]
            split[f"{mode}_{group}_miou"] = scored_mean(ious)
            split[f"{mode}_{group}_views"] = sum(i is not None for i in ious)
    report.views.extend(rows)
    miou = scored_mean([r["iou"] for r in rows])
    macc = scored_mean([r["acc"] for r in rows])
    if mode == "coarse":
        report.miou, report.macc = miou, macc
    return miou, macc


def summarize(reports: list[SceneReport]) -> dict:
    """Dataset-level numbers: means over the scenes that finished, all of one protocol (results
    of different protocols are never averaged)."""
    ok = [r for r in reports if r.status == "ok" and r.miou is not None]
    protocols = sorted({r.protocol for r in ok if r.protocol})
    if len(protocols) > 1:
        raise ValueError(f"scenes of different protocols {protocols} cannot be averaged")

    def mean(key):
        vals = [getattr(r, key) for r in ok if getattr(r, key) is not None]
        return float(np.mean(vals)) if vals else None

    timing_keys = sorted({k for r in ok for k in r.timings})
    return {
        "protocol_id": protocols[0] if protocols else None,
        "miou": mean("miou"),
        "macc": mean("macc"),
        "segmenter_miou": mean("segmenter_miou"),
        "refined_miou": mean("refined_miou"),
        "refined_macc": mean("refined_macc"),
        "scenes_scored": len(ok),
        "scenes_failed": [r.scene for r in reports if r.status != "ok"],
        "partial": len(ok) < len(reports),
        "timings": {
            k: float(np.mean([r.timings[k] for r in ok if k in r.timings])) for k in timing_keys
        },
    }
