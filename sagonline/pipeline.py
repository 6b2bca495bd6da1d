"""Stage I for one scene: render the trajectory, segment it, vote, render labels, score.

Every stage's output is cached in `cache_dir` under a key of the content it consumed (scene
parameters, cameras, prompt, segmenter settings and weights, vote settings, the stage's code
version; see `stage_keys`), so an interrupted run resumes from the last finished stage and a
changed input recomputes exactly the stages that depend on it. Timings are wall seconds of
work done by this run; a stage taken from the cache reports `cached` in `report.stages` and its
original timing under `report.cached_timings`, never as this run's time.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from sagonline.consensus import VoteConfig, VoteResult, consensus_vote
from sagonline.datasets.base import DatasetError, SceneTask
from sagonline.feedback import FeedbackConfig, segment_with_feedback
from sagonline.io import store
from sagonline.metrics import labels3d_metrics, match_and_relabel, view_metrics
from sagonline.provenance import (
    STAGE_VERSIONS,
    digest_arrays,
    digest_cameras,
    digest_gaussians,
    digest_json,
)
from sagonline.recording import Recorder
from sagonline.render.api import render, render_labels, resolve_backend, to_uint8
from sagonline.segmenters.base import SegmentationResult, VideoSegmenter
from sagonline.trajectory import nearest_view


@dataclass
class PipelineSettings:
    backend: str = "auto"  # the compiled kernel on the CPU, gsplat on CUDA, else PyTorch
    device: str = "cpu"
    label_min_weight: float = 0.2
    resize: str = "pred_to_gt"
    progress: bool = True
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)


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

    def add_timings(self, stages: tuple[str, ...], **times: float) -> None:
        """This run's timings when it computed every one of `stages`, else the cached run's
        (kept apart, under `cached_timings`)."""
        fresh = all(self.stages.get(s) == "computed" for s in stages)
        (self.timings if fresh else self.cached_timings).update(times)


@dataclass
class StageOneOutput:
    """What Stage I hands to Stage II: the trajectory's frames (T RGB uint8 images), the
    segmenter's masks, the label count, the three stage keys, and the names of the views whose
    masks voted."""

    frames: list[np.ndarray]
    segmentation: SegmentationResult
    num_labels: int
    keys: dict[str, str]
    voted: set[str]


def input_digests(task: SceneTask) -> dict:
    """Content digests of everything a scene's numbers depend on, besides the settings."""
    return {
        "scene": digest_gaussians(task.gaussians),
        "trajectory_cameras": digest_cameras(task.trajectory),
        "eval_cameras": digest_cameras(v.camera for v in task.eval_views),
        "eval_ground_truth": digest_arrays(v.gt for v in task.eval_views),
        "trajectory_ground_truth": digest_arrays(task.trajectory_gt or []),
        "prompt": task.prompt.digest(),
        "ignore_label": task.ignore_label,
        "num_labels": task.num_labels,
    }


def stage_keys(
    inputs: dict,
    settings: PipelineSettings,
    segmenter_key: dict,
    vote_cfg: VoteConfig,
) -> dict[str, str]:
    """Cache keys of the three cached stages, each a digest of exactly what the stage consumes
    (and, through the upstream key, of what its inputs were made from):
    frames <- scene, trajectory cameras, renderer, background, device;
    masks  <- frames, prompt, trajectory ground truth (the oracle reads it), segmenter settings
              and weight digests (with consensus feedback also what the vote below reads);
    vote   <- masks, scene, trajectory cameras, label count, vote settings, renderer."""
    backend = resolve_backend(settings.backend, settings.device)
    device = torch.device(settings.device).type
    frames = digest_json(
        "frames", STAGE_VERSIONS["frames"], inputs["scene"], inputs["trajectory_cameras"],
        backend, list(settings.background), device,
    )  # fmt: skip
    feedback = []  # with consensus feedback the masks also depend on the vote and its render
    if settings.feedback.enabled:
        feedback = [
            asdict(settings.feedback), asdict(vote_cfg), inputs["scene"],
            inputs["trajectory_cameras"], inputs["num_labels"], settings.label_min_weight,
        ]  # fmt: skip
    masks = digest_json(
        "masks", STAGE_VERSIONS["masks"], frames, inputs["prompt"],
        inputs["trajectory_ground_truth"], segmenter_key, *feedback,
    )  # fmt: skip
    vote = digest_json(
        "vote", STAGE_VERSIONS["vote"], masks, inputs["scene"], inputs["trajectory_cameras"],
        inputs["num_labels"], asdict(vote_cfg), backend, device,
    )  # fmt: skip
    return {"frames": frames, "masks": masks, "vote": vote}


class StageCache:
    """`<dir>/<stage>-<key>.store` files (`sagonline.io.store`: arrays and JSON, never a
    pickle, each checked against the digest of its own bytes) written atomically; a missing dir
    disables caching. A damaged or foreign entry is named, removed and recomputed, never used."""

    def __init__(self, directory: str | Path | None):
        self.dir = Path(directory) if directory is not None else None

    def path(self, stage: str, key: str) -> Path | None:
        return None if self.dir is None else self.dir / f"{stage}-{key}{store.SUFFIX}"

    def load(self, stage: str, key: str):
        path = self.path(stage, key)
        return None if path is None else store.load_or_discard(path, "cache entry")

    def save(self, stage: str, key: str, value) -> None:
        if self.dir is not None:
            store.save(self.path(stage, key), value)


def render_frames(task: SceneTask, settings: PipelineSettings) -> tuple[list[np.ndarray], float]:
    """RGB uint8 frames of the trajectory and the mean seconds per frame."""
    g = task.gaussians.to(settings.device)
    bg = torch.tensor(settings.background)
    frames, start = [], time.perf_counter()
    for cam in tqdm(
        task.trajectory, desc=f"{task.name}: render", leave=False, disable=not settings.progress
    ):
        frames.append(to_uint8(render(g, cam, background=bg, backend=settings.backend).rgb))
    return frames, (time.perf_counter() - start) / max(len(frames), 1)


def run_stage_one(
    task: SceneTask,
    segmenter: VideoSegmenter,
    vote_cfg: VoteConfig,
    settings: PipelineSettings,
    *,
    segmenter_key: dict | None = None,
    cache_dir: str | Path | None = None,
    recorder: Recorder | None = None,
) -> tuple[SceneReport, VoteResult, StageOneOutput]:
    """Run and score Stage I on one scene. Returns the report, the vote, and what Stage II
    (refinement) reuses."""
    recorder = recorder or Recorder(None)
    cache = StageCache(cache_dir)
    report = SceneReport(scene=task.name)
    report.extra["empty_ground_truth_views"] = check_ground_truth(task)
    fit = task.meta.get("fit")
    if fit:
        report.extra["fit"] = fit
        if fit.get("stopped") == "time_budget":
            warnings.warn(
                f"{task.dataset}/{task.name}: its scene was fitted under a time budget and stopped "
                f"after {fit.get('iterations')} of {fit.get('iterations_planned')} iterations "
                f"({fit['path']}); its numbers depend on how busy that machine was",
                stacklevel=2,
            )
    report.inputs = input_digests(task)
    keys = stage_keys(report.inputs, settings, segmenter_key or {"name": segmenter.name}, vote_cfg)

    def cached_or_run(stage: str, compute):
        value = cache.load(stage, keys[stage])
        report.stages[stage] = "computed" if value is None else "cached"
        if value is None:
            value = compute()
            cache.save(stage, keys[stage], value)
        return value

    frames, sec = cached_or_run("frames", lambda: render_frames(task, settings))
    seg = cached_or_run(
        "masks", lambda: segment_frames(task, segmenter, frames, settings, vote_cfg)
    )
    if "feedback" in seg.info:
        report.extra["feedback"] = seg.info["feedback"]
    report.inputs["masks"] = digest_arrays(seg.masks)
    report.add_timings(("frames",), render_ms_per_frame=1000 * sec)
    report.add_timings(("masks",), segment_ms_per_frame=seg.ms_per_frame)
    # Time to first mask: render the prompt frame, then the segmenter answers on it.
    report.add_timings(
        ("frames", "masks"), time_to_first_mask_s=sec + seg.seconds[task.prompt.frame]
    )

    names = task.label_names or ["background"] + [str(i) for i in range(1, task.num_labels)]
    num_labels = max(task.num_labels, 1 + max(int(m.max()) for m in seg.masks))
    recorder.annotate(task.name, names + [f"id {i}" for i in range(len(names), num_labels)])
    for i, (frame, mask) in enumerate(zip(frames, seg.masks, strict=True)):
        recorder.trajectory_frame(task.name, i, frame, mask, camera=task.trajectory[i])

    automatic = not task.prompt.objects and not task.prompt.texts
    if task.trajectory_gt is not None:
        seg_masks = seg.masks
        if automatic:  # arbitrary ids: match them to the ground truth once per scene
            seg_masks = match_and_relabel(
                seg.masks, task.trajectory_gt, settings.resize, task.ignore_label
            )
        report.segmenter_miou = float(
            np.mean(
                [
                    view_metrics(m, g, settings.resize, task.ignore_label)["iou"]
                    for m, g in zip(seg_masks, task.trajectory_gt, strict=True)
                ]
            )
        )

    vote = cached_or_run(
        "vote",
        lambda: consensus_vote(
            task.gaussians.to(settings.device),
            task.trajectory,
            seg.masks,
            num_labels,
            vote_cfg,
            backend=settings.backend,
            progress=settings.progress,
        ),
    )
    report.vote = {k: v for k, v in vote.stats.items() if k != "aggregation_s"}
    report.add_timings(
        ("vote",), vote_s=vote.stats["aggregation_s"], vote_ms_per_mask=vote.stats["ms_per_mask"]
    )

    voted = {task.trajectory[i].name for i in vote.frames}
    score_views(task, vote, settings, report, recorder, num_labels, automatic, voted=voted)
    if task.gt_labels3d is not None and not automatic:
        report.labels3d = labels3d_metrics(vote.labels, vote.labelled, task.gt_labels3d, num_labels)
    recorder.gaussians(
        task.name,
        task.gaussians,
        vote.labels.cpu().numpy(),
        vote.labelled.cpu().numpy(),
        vote.histogram.cpu().numpy(),
    )
    return report, vote, StageOneOutput(frames, seg, num_labels, keys, voted)


def segment_frames(
    task: SceneTask,
    segmenter: VideoSegmenter,
    frames: list[np.ndarray],
    settings: PipelineSettings,
    vote_cfg: VoteConfig,
) -> SegmentationResult:
    """The segmenter's masks of the rendered trajectory, with consensus feedback when it is on
    (`settings.feedback`)."""
    if not settings.feedback.enabled:
        return segmenter.segment(frames, task.prompt, ground_truth=task.trajectory_gt)
    seg, _ = segment_with_feedback(
        segmenter,
        frames,
        task.prompt,
        task.gaussians.to(settings.device),
        task.trajectory,
        task.num_labels,
        vote_cfg,
        settings.feedback,
        backend=settings.backend,
        min_weight=settings.label_min_weight,
        ground_truth=task.trajectory_gt,
    )
    return seg


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


def score_views(
    task: SceneTask,
    vote: VoteResult,
    settings: PipelineSettings,
    report: SceneReport,
    recorder: Recorder,
    num_labels: int | None = None,
    automatic: bool = False,
    mode: str = "initial",
    voted: set[str] | None = None,
) -> list[np.ndarray]:
    """Render the fused labels at every eval view and score them against the ground truth.
    With `automatic` (arbitrary segmenter ids), labels are first matched to the ground truth
    once for the whole scene."""
    g = task.gaussians.to(settings.device)
    num_labels = num_labels or task.num_labels
    preds, seconds = [], []
    for view in tqdm(
        task.eval_views, desc=f"{task.name}: score", leave=False, disable=not settings.progress
    ):
        start = time.perf_counter()
        preds.append(
            render_labels(
                g,
                view.camera,
                vote.labels,
                num_labels,
                labelled=vote.labelled,
                min_weight=settings.label_min_weight,
                backend=settings.backend,
            )
            .cpu()
            .numpy()
        )
        seconds.append(time.perf_counter() - start)
    if automatic and preds:
        preds = match_and_relabel(
            preds, [v.gt for v in task.eval_views], settings.resize, task.ignore_label
        )
        report.extra["label_matching"] = "hungarian, scene-wide"
    record_scores(task, preds, settings, report, mode, voted)
    report.timings["label_render_ms_per_frame"] = 1000 * float(np.mean(seconds)) if seconds else 0
    if recorder.enabled:
        ious = [r["iou"] for r in report.views[-len(preds) :]] if preds else []
        frames = nearest_frames(task)
        for i, (view, pred) in enumerate(zip(task.eval_views, preds, strict=True)):
            rgb = to_uint8(render(g, view.camera, backend=settings.backend).rgb)
            recorder.eval_view(
                task.name, i, rgb, pred, view.gt, camera=view.camera, iou=ious[i], frame=frames[i]
            )
    return preds


def nearest_frames(task: SceneTask) -> list[int]:
    """For each eval view, the trajectory frame of the same name, else the nearest by camera
    centre (where the recording shows it on the `frame` timeline)."""
    index = {c.name: i for i, c in enumerate(task.trajectory)}
    centres = torch.stack([c.center for c in task.trajectory])
    return [
        index.get(v.name, int((centres - v.camera.center).norm(dim=1).argmin()))
        for v in task.eval_views
    ]


def record_scores(
    task: SceneTask,
    preds: list[np.ndarray],
    settings: PipelineSettings,
    report: SceneReport,
    mode: str,
    voted: set[str] | None = None,
) -> tuple[float, float]:
    """Per-view rows for `mode` ("initial" or "refined") and their means; the initial mode's
    means are the report's `miou`/`macc`. `voted`: names of the views whose masks voted (a
    row says whether its view is one of them)."""
    rows = []
    for view, pred in zip(task.eval_views, preds, strict=True):
        m = view_metrics(pred, view.gt, settings.resize, task.ignore_label)
        rows.append(
            {
                "scene": task.name,
                "view": view.name,
                "mode": mode,
                "iou": m["iou"],
                "acc": m["acc"],
                "voted": view.name in (voted or ()),
            }
        )
    photos = set(task.meta.get("photographs") or ())
    if photos and rows:  # captures with photographs for some views only (mold_cape)
        photo_cams = [c for c in task.trajectory if c.name in photos]
        angle, dist = nearest_view([v.camera for v in task.eval_views], photo_cams)
        for row, a, d in zip(rows, angle, dist, strict=True):
            row["photographed"] = row["view"] in photos
            row["photo_angle_deg"] = 0.0 if row["photographed"] else float(a)
            row["photo_distance"] = 0.0 if row["photographed"] else float(d)
        split = report.extra.setdefault("by_view_kind", {})
        for kind, want in (("photographed", True), ("mask_only", False)):
            ious = [r["iou"] for r in rows if r["photographed"] is want]
            split[f"{mode}_{kind}_miou"] = float(np.mean(ious)) if ious else None
            split[f"{mode}_{kind}_views"] = len(ious)
    report.views.extend(rows)
    miou = float(np.mean([r["iou"] for r in rows])) if rows else None
    macc = float(np.mean([r["acc"] for r in rows])) if rows else None
    if mode == "initial":
        report.miou, report.macc = miou, macc
    return miou, macc


def run_stage_two(
    task: SceneTask,
    vote: VoteResult,
    stage_one: StageOneOutput,
    refine_cfg,
    settings: PipelineSettings,
    report: SceneReport,
    recorder: Recorder,
    checkpoint: str | Path | None = None,
) -> None:
    """Train the student in the background while the initial mode keeps answering the eval
    views, then answer them again in refined mode; both are scored into `report`."""
    from sagonline.refine import RefinementTrainer
    from sagonline.refine.service import OnlineSegmentation

    num_labels = stage_one.num_labels
    g = task.gaussians.to(settings.device)
    service = OnlineSegmentation(
        g,
        vote.labels,
        vote.labelled,
        num_labels,
        backend=settings.backend,
        min_weight=settings.label_min_weight,
    )
    coarse = [service.coarse(c) for c in task.trajectory]
    trainer = RefinementTrainer(
        refine_cfg,
        num_labels,
        stage_one.frames,
        coarse,
        stage_one.segmentation.masks,
        checkpoint,
    )
    service.trainer = trainer
    start = time.perf_counter()
    resumed_done = trainer.done.is_set()
    trainer.start()
    initial = []  # the initial mode keeps answering while the student trains
    while True:
        for view in task.eval_views:
            answer = service.answer(view.camera)
            if answer.mode == "initial":
                initial.append(answer.ms)
            if trainer.done.is_set():
                break
        if trainer.done.is_set() and initial:
            break
        if trainer.done.is_set():  # resumed from a finished checkpoint: time one pass anyway
            initial += [service.answer(v.camera, "initial").ms for v in task.eval_views]
            break
    trainer.wait()
    switched = time.perf_counter() - start
    answers = [service.answer(v.camera) for v in task.eval_views]
    assert all(a.mode == "refined" for a in answers)
    preds = [a.mask for a in answers]
    if not task.prompt.objects and not task.prompt.texts and preds:
        preds = match_and_relabel(
            preds, [v.gt for v in task.eval_views], settings.resize, task.ignore_label
        )
    report.refined_miou, report.refined_macc = record_scores(
        task, preds, settings, report, "refined", stage_one.voted
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
        "encoder": refine_cfg.encoder,
    }
    if recorder.enabled:
        ious = [r["iou"] for r in report.views[-len(preds) :]] if preds else []
        frames = nearest_frames(task)
        for i, pred in enumerate(preds):
            recorder.refined_view(task.name, i, pred, iou=ious[i], frame=frames[i])


def summarize(reports: list[SceneReport]) -> dict:
    """Dataset-level numbers: means over the scenes that finished."""
    ok = [r for r in reports if r.status == "ok" and r.miou is not None]

    def mean(key):
        vals = [getattr(r, key) for r in ok if getattr(r, key) is not None]
        return float(np.mean(vals)) if vals else None

    timing_keys = sorted({k for r in ok for k in r.timings})
    return {
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


__all__ = [
    "PipelineSettings",
    "SceneReport",
    "SegmentationResult",
    "StageOneOutput",
    "StageCache",
    "run_stage_one",
    "summarize",
]
