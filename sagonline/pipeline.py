"""Stage I for one scene: render the trajectory, segment it, vote, render labels, score.

Every stage's output is cached in `cache_dir` under a key of the settings that produced it, so
an interrupted run resumes from the last finished stage and a changed setting recomputes only
what depends on it. Timings are wall seconds per stage.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from sagonline.consensus import VoteConfig, VoteResult, consensus_vote
from sagonline.datasets.base import SceneTask
from sagonline.metrics import labels3d_metrics, match_and_relabel, view_metrics
from sagonline.recording import Recorder
from sagonline.render.api import render, render_labels, to_uint8
from sagonline.segmenters.base import SegmentationResult, VideoSegmenter


@dataclass
class PipelineSettings:
    backend: str = "torch"
    device: str = "cpu"
    label_min_weight: float = 0.2
    resize: str = "pred_to_gt"
    progress: bool = True
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)


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


def settings_key(*parts) -> str:
    """Short stable hash of JSON-able settings (the cache key of a stage)."""
    blob = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:12]


class StageCache:
    """`<dir>/<stage>-<key>.pt` files written atomically; a missing dir disables caching."""

    def __init__(self, directory: str | Path | None):
        self.dir = Path(directory) if directory is not None else None

    def load(self, stage: str, key: str):
        if self.dir is None:
            return None
        path = self.dir / f"{stage}-{key}.pt"
        return torch.load(path, weights_only=False) if path.is_file() else None

    def save(self, stage: str, key: str, value) -> None:
        if self.dir is None:
            return
        self.dir.mkdir(parents=True, exist_ok=True)
        path = self.dir / f"{stage}-{key}.pt"
        tmp = path.with_name(path.name + ".tmp")
        torch.save(value, tmp)
        tmp.replace(path)


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
) -> tuple[SceneReport, VoteResult, dict]:
    """Run and score Stage I on one scene. Returns the report, the vote, and the artefacts
    (frames, masks) that later stages (refinement) reuse."""
    recorder = recorder or Recorder(None)
    cache = StageCache(cache_dir)
    report = SceneReport(scene=task.name)
    scene_key = settings_key(
        task.dataset, task.name, task.meta, settings.backend, settings.background
    )

    cached = cache.load("frames", scene_key)
    if cached is None:
        frames, sec = render_frames(task, settings)
        cache.save("frames", scene_key, {"frames": frames, "sec": sec})
    else:
        frames, sec = cached["frames"], cached["sec"]
    report.timings["render_ms_per_frame"] = 1000 * sec

    seg_key = settings_key(scene_key, segmenter_key or segmenter.name)
    cached = cache.load("masks", seg_key)
    if cached is None:
        seg = segmenter.segment(frames, task.prompt, ground_truth=task.trajectory_gt)
        cache.save("masks", seg_key, seg)
    else:
        seg = cached
    report.timings["segment_ms_per_frame"] = seg.ms_per_frame
    # Time to first mask: render the prompt frame, then the segmenter answers on it.
    report.timings["time_to_first_mask_s"] = sec + seg.seconds[task.prompt.frame]
    automatic = not task.prompt.objects and not task.prompt.texts
    if task.trajectory_gt is not None:
        seg_masks = seg.masks
        if automatic:  # arbitrary ids: match them to the ground truth once per scene
            seg_masks = match_and_relabel(seg.masks, task.trajectory_gt, settings.resize)
        report.segmenter_miou = float(
            np.mean(
                [
                    view_metrics(m, g, settings.resize)["iou"]
                    for m, g in zip(seg_masks, task.trajectory_gt, strict=True)
                ]
            )
        )
    num_labels = max(task.num_labels, 1 + max(int(m.max()) for m in seg.masks))

    vote_key = settings_key(seg_key, asdict(vote_cfg))
    vote = cache.load("vote", vote_key)
    if vote is None:
        vote = consensus_vote(
            task.gaussians.to(settings.device),
            task.trajectory,
            seg.masks,
            num_labels,
            vote_cfg,
            backend=settings.backend,
            progress=settings.progress,
        )
        cache.save("vote", vote_key, vote)
    report.vote = {k: v for k, v in vote.stats.items() if k != "aggregation_s"}
    report.timings["vote_s"] = vote.stats["aggregation_s"]
    report.timings["vote_ms_per_mask"] = vote.stats["ms_per_mask"]

    names = task.label_names or ["background"] + [str(i) for i in range(1, task.num_labels)]
    recorder.annotate(task.name, names + [f"id {i}" for i in range(len(names), num_labels)])
    for i, (frame, mask) in enumerate(zip(frames, seg.masks, strict=True)):
        recorder.trajectory_frame(task.name, i, frame, mask)

    score_views(task, vote, settings, report, recorder, num_labels, automatic)
    if task.gt_labels3d is not None and not automatic:
        report.labels3d = labels3d_metrics(vote.labels, vote.labelled, task.gt_labels3d, num_labels)
    recorder.gaussians(
        task.name,
        task.gaussians.means.cpu().numpy(),
        vote.labels.cpu().numpy(),
        vote.labelled.cpu().numpy(),
    )
    return report, vote, {"frames": frames, "segmentation": seg, "num_labels": num_labels}


def score_views(
    task: SceneTask,
    vote: VoteResult,
    settings: PipelineSettings,
    report: SceneReport,
    recorder: Recorder,
    num_labels: int | None = None,
    automatic: bool = False,
    mode: str = "initial",
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
        preds = match_and_relabel(preds, [v.gt for v in task.eval_views], settings.resize)
        report.extra["label_matching"] = "hungarian, scene-wide"
    record_scores(task, preds, settings, report, mode)
    report.timings["label_render_ms_per_frame"] = 1000 * float(np.mean(seconds)) if seconds else 0
    if recorder.enabled:
        for i, (view, pred) in enumerate(zip(task.eval_views, preds, strict=True)):
            rgb = to_uint8(render(g, view.camera, backend=settings.backend).rgb)
            recorder.eval_view(task.name, i, rgb, pred, view.gt)
    return preds


def record_scores(
    task: SceneTask,
    preds: list[np.ndarray],
    settings: PipelineSettings,
    report: SceneReport,
    mode: str,
) -> tuple[float, float]:
    """Per-view rows for `mode` ("initial" or "refined") and their means; the initial mode's
    means are the report's `miou`/`macc`."""
    rows = []
    for view, pred in zip(task.eval_views, preds, strict=True):
        m = view_metrics(pred, view.gt, settings.resize)
        rows.append(
            {"scene": task.name, "view": view.name, "mode": mode, "iou": m["iou"], "acc": m["acc"]}
        )
    report.views.extend(rows)
    miou = float(np.mean([r["iou"] for r in rows])) if rows else None
    macc = float(np.mean([r["acc"] for r in rows])) if rows else None
    if mode == "initial":
        report.miou, report.macc = miou, macc
    return miou, macc


def run_stage_two(
    task: SceneTask,
    vote: VoteResult,
    artefacts: dict,
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

    num_labels = artefacts["num_labels"]
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
        artefacts["frames"],
        coarse,
        artefacts["segmentation"].masks,
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
        preds = match_and_relabel(preds, [v.gt for v in task.eval_views], settings.resize)
    report.refined_miou, report.refined_macc = record_scores(
        task, preds, settings, report, "refined"
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
        for i, pred in enumerate(preds):
            recorder.refined_view(task.name, i, pred)


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
    "StageCache",
    "run_stage_one",
    "summarize",
]
