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
from sagonline.metrics import labels3d_metrics, view_metrics
from sagonline.recording import Recorder
from sagonline.render.api import render, render_labels
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


def to_uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


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
    if task.trajectory_gt is not None:
        report.segmenter_miou = float(
            np.mean(
                [
                    view_metrics(m, g, settings.resize)["iou"]
                    for m, g in zip(seg.masks, task.trajectory_gt, strict=True)
                ]
            )
        )

    vote_key = settings_key(seg_key, asdict(vote_cfg))
    vote = cache.load("vote", vote_key)
    if vote is None:
        vote = consensus_vote(
            task.gaussians.to(settings.device),
            task.trajectory,
            seg.masks,
            task.num_labels,
            vote_cfg,
            backend=settings.backend,
            progress=settings.progress,
        )
        cache.save("vote", vote_key, vote)
    report.vote = {k: v for k, v in vote.stats.items() if k != "aggregation_s"}
    report.timings["vote_s"] = vote.stats["aggregation_s"]
    report.timings["vote_ms_per_mask"] = vote.stats["ms_per_mask"]

    recorder.annotate(
        task.name, task.label_names or ["background"] + [str(i) for i in range(1, task.num_labels)]
    )
    for i, (frame, mask) in enumerate(zip(frames, seg.masks, strict=True)):
        recorder.trajectory_frame(task.name, i, frame, mask)

    score_views(task, vote, settings, report, recorder)
    if task.gt_labels3d is not None:
        report.labels3d = labels3d_metrics(
            vote.labels, vote.labelled, task.gt_labels3d, task.num_labels
        )
    recorder.gaussians(
        task.name,
        task.gaussians.means.cpu().numpy(),
        vote.labels.cpu().numpy(),
        vote.labelled.cpu().numpy(),
    )
    return report, vote, {"frames": frames, "segmentation": seg}


def score_views(
    task: SceneTask,
    vote: VoteResult,
    settings: PipelineSettings,
    report: SceneReport,
    recorder: Recorder,
) -> list[np.ndarray]:
    """Render the fused labels at every eval view and score them against the ground truth."""
    g = task.gaussians.to(settings.device)
    preds, seconds = [], []
    for i, view in enumerate(
        tqdm(
            task.eval_views, desc=f"{task.name}: score", leave=False, disable=not settings.progress
        )
    ):
        start = time.perf_counter()
        pred = (
            render_labels(
                g,
                view.camera,
                vote.labels,
                task.num_labels,
                labelled=vote.labelled,
                min_weight=settings.label_min_weight,
                backend=settings.backend,
            )
            .cpu()
            .numpy()
        )
        seconds.append(time.perf_counter() - start)
        m = view_metrics(pred, view.gt, settings.resize)
        report.views.append(
            {
                "scene": task.name,
                "view": view.name,
                "mode": "initial",
                "iou": m["iou"],
                "acc": m["acc"],
            }
        )
        preds.append(pred)
        if recorder.enabled:
            rgb = to_uint8(render(g, view.camera, backend=settings.backend).rgb)
            recorder.eval_view(task.name, i, rgb, pred, view.gt)
    ious = [v["iou"] for v in report.views if v["mode"] == "initial"]
    accs = [v["acc"] for v in report.views if v["mode"] == "initial"]
    report.miou = float(np.mean(ious)) if ious else None
    report.macc = float(np.mean(accs)) if accs else None
    report.timings["label_render_ms_per_frame"] = 1000 * float(np.mean(seconds)) if seconds else 0
    return preds


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
