"""Stage I for one scene: frames -> masks -> vote (cached stages), then score and record.

`run_scene` composes the stages of `stages.py`; each is cached under a key derived from its
inputs (`graph.py`), so an interrupted run resumes from the last finished stage and a changed
input recomputes exactly the stages that depend on it. Timings are wall seconds of work done by
this run; a stage taken from the cache reports `cached` in `report.stages` and its original
timing under `report.cached_timings`, never as this run's time.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from sagonline.core.progress import progress
from sagonline.core.provenance import digest_arrays, digest_cameras, digest_gaussians
from sagonline.datasets.base import SceneTask
from sagonline.pipeline.diagnose import SceneDiagnosis
from sagonline.pipeline.events import StageOneBars
from sagonline.pipeline.graph import StageCache
from sagonline.pipeline.scoring import (
    SceneReport,
    check_ground_truth,
    is_automatic,
    record_scores,
    segmenter_miou,
)
from sagonline.pipeline.stage_one import (
    MaskReady,
    PipelineSettings,
    StageOne,
    StageOneConfig,
    StageOneOutput,
)
from sagonline.pipeline.stages import SegmenterRun
from sagonline.record.recording import Recorder
from sagonline.render.api import capable_backend, render, render_labels_and_surface, to_uint8
from sagonline.render.backends import resolve_backend
from sagonline.render.rasterize import RenderOutput
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.score.metrics import labels3d_metrics
from sagonline.segment.base import VideoSegmenter
from sagonline.vote.consensus import VoteConfig, VoteResult


def input_digests(task: SceneTask) -> dict:
    """Content digests of everything a scene's numbers depend on, besides the settings (what a
    finished run records, to refuse a rerun on changed data)."""
    return {
        "scene": digest_gaussians(task.gaussians),
        "trajectory_cameras": digest_cameras(task.trajectory),
        "eval_cameras": digest_cameras(v.camera for v in task.eval_views),
        "eval_ground_truth": digest_arrays((v.gt for v in task.eval_views), as_int64=True),
        "trajectory_ground_truth": digest_arrays(task.trajectory_gt or [], as_int64=True),
        "prompt": task.prompt.digest(),
        "ignore_label": task.ignore_label,
        "num_labels": task.num_labels,
    }


def run_scene(
    task: SceneTask,
    segmenter: SegmenterRun | VideoSegmenter,
    vote: VoteConfig,
    settings: PipelineSettings,
    *,
    cache_dir: str | Path | None = None,
    recorder: Recorder | None = None,
    predictions_to: str | Path | None = None,
) -> tuple[SceneReport, StageOneOutput]:
    """Run and score Stage I on one scene: its report, and what Stage II reuses.
    `predictions_to`: a run folder to write the scored label maps into (PNG, see
    `sagonline.score.predictions`)."""
    recorder = recorder or Recorder(None)
    settings = task_settings(task, settings)
    if isinstance(segmenter, VideoSegmenter):
        segmenter = SegmenterRun(segmenter)
    report = SceneReport(scene=task.name, inputs=input_digests(task))
    report.extra["empty_ground_truth_views"] = check_ground_truth(task)
    note_fit(task, report)
    if any(settings.background):
        report.extra["render_background"] = list(settings.background)
    g = task.gaussians.to(settings.device)
    cache = StageCache(cache_dir)
    engine = StageOne(
        StageOneConfig(
            g,
            task.trajectory,
            segmenter,
            vote,
            settings,
            task.num_labels,
            task.trajectory_gt,
            cache,
        ),
        task.prompt,
    )
    stage_one = follow_stage_one(task, engine, recorder, settings.progress)
    report.stages = {k: v.status for k, v in stage_one.runs.items()}
    plan = stage_one.backends
    report.extra["backends"] = plan.describe()
    report.stage_keys = stage_one.keys
    num_labels, result = stage_one.num_labels, stage_one.vote.value
    note_stage_one(task, report, stage_one, settings.metrics.resize)
    diagnose = settings.diagnose and not is_automatic(task)
    preds, surfaces = score_views(
        task,
        g,
        result,
        num_labels,
        settings,
        report,
        stage_one.voted,
        predictions_to,
        backend=plan.labels,
        keep_surfaces=diagnose,
    )
    if task.gt_labels3d is not None and not is_automatic(task):
        report.labels3d = labels3d_metrics(result.labels, task.gt_labels3d, num_labels)
    diagnosis = None
    if diagnose:
        diagnosis = SceneDiagnosis(task, g, stage_one, segmenter, vote, settings, report, cache)
    record_eval_views(
        task,
        recorder,
        preds,
        report,
        g,
        plan.images,
        diagnosis,
        settings.background,
        surfaces,
        stage_one.frames.value.images,
    )
    recorder.gaussians(
        task.name, task.gaussians, result.labels.cpu().numpy(), result.histogram.cpu().numpy()
    )
    return report, stage_one


def task_settings(task: SceneTask, settings: PipelineSettings) -> PipelineSettings:
    """`settings` for `task`: its scene rendered on the colour it was fitted on, if known."""
    if task.background is None:
        return settings
    return replace(settings, background=task.background)


def follow_stage_one(
    task: SceneTask, engine: StageOne, recorder: Recorder, show: bool
) -> StageOneOutput:
    """Drain the engine's stream: progress said (frames, then masks and votes), each frame and
    mask recorded as it comes (an interrupted run keeps them), the stages' outputs."""
    names = task.label_names or ["background"] + [str(i) for i in range(1, task.num_labels)]
    recorder.annotate(task.name, names)
    n = len(task.trajectory)
    bars = StageOneBars(n, f"{task.name}: ", enabled=show)
    for event in engine.stream():
        bars.update(event)
        if isinstance(event, MaskReady):
            recorder.trajectory_frame(
                task.name,
                event.index,
                engine.frames[event.index],
                event.mask,
                camera=task.trajectory[event.index],
            )
    bars.close()
    out = engine.result()
    recorder.annotate(task.name, names + [f"id {i}" for i in range(len(names), out.num_labels)])
    return out


def note_fit(task: SceneTask, report: SceneReport) -> None:
    """Record how the scene was fitted; warn when its fit stopped on a time budget."""
    fit = task.meta.get("fit")
    if not fit:
        return
    report.extra["fit"] = fit
    if fit.get("stopped") == "time_budget":
        warnings.warn(
            f"{task.dataset}/{task.name}: its scene was fitted under a time budget and stopped "
            f"after {fit.get('iterations')} of {fit.get('iterations_planned')} iterations "
            f"({fit['path']}); its numbers depend on how busy that machine was",
            stacklevel=3,
        )


def note_stage_one(
    task: SceneTask, report: SceneReport, stage_one: StageOneOutput, resize: str
) -> None:
    """The stages' timings (this run's, or the cached run's apart), the vote's statistics,
    the segmenter's own mIoU and the digest of its masks."""
    seg, result = stage_one.masks.value, stage_one.vote.value
    sec = stage_one.frames.value.seconds_per_frame
    if "feedback" in seg.info:
        report.extra["feedback"] = seg.info["feedback"]
    described = {k: v for k, v in seg.info.items() if k not in ("order", "feedback")}
    if described:  # what the segmenter says of itself: its weights' SHA-256, its prompting
        report.extra["segmenter"] = described
    report.inputs["masks"] = digest_arrays(seg.masks, as_int64=True)  # as before narrow masks
    report.add_timings(("frames",), render_ms_per_frame=1000 * sec)
    report.add_timings(("masks",), segment_ms_per_frame=seg.ms_per_frame)
    # Time to first mask: render the prompt frame, then the segmenter answers on it.
    report.add_timings(
        ("frames", "masks"), time_to_first_mask_s=sec + seg.seconds[task.prompt.frame]
    )
    report.segmenter_miou = segmenter_miou(task, seg.masks, resize)
    report.vote = {k: v for k, v in result.stats.items() if k != "aggregation_s"}
    report.add_timings(
        ("vote",),
        vote_s=result.stats["aggregation_s"],
        vote_ms_per_mask=result.stats["ms_per_mask"],
    )


# The eval views' surfaces `score_views` keeps for their diagnosis, at most (a 1 MP view's is
# 16 MB); past it the diagnosis draws each again, a walk a view
SURFACES_KEPT_BYTES = 512 * 2**20


def score_views(
    task: SceneTask,
    g: Gaussians,
    vote: VoteResult,
    num_labels: int,
    settings: PipelineSettings,
    report: SceneReport,
    voted: set[str],
    save_to: str | Path | None = None,
    *,
    backend: str = "auto",
    keep_surfaces: bool = False,
) -> tuple[list[np.ndarray], list[RenderOutput | None]]:
    """Render the fused labels at every eval view (by `backend`'s label walk, at the size
    `settings.label_render.size` names), score them (the coarse mode) and time the label render;
    returns the (H, W) predictions and, with `keep_surfaces`, each view's surface for its
    diagnosis where the compiled kernel's label walk drew it at the eval camera (alpha, depth
    and ids, no colours; None elsewhere and past SURFACES_KEPT_BYTES in all, where the diagnosis
    draws them again). g: the scene on `settings.device`."""
    preds, seconds, surfaces, kept = [], [], [], 0
    for view in progress(
        task.eval_views, f"{task.name}: score", len(task.eval_views), enabled=settings.progress
    ):
        start = time.perf_counter()
        camera = settings.scored_camera(view)
        pred, surface = render_labels_and_surface(
            g,
            camera,
            vote.labels,
            num_labels,
            min_weight=settings.label_render.min_weight,
            backend=backend,
        )
        preds.append(pred.cpu().numpy())
        seconds.append(time.perf_counter() - start)
        size = 16 * camera.width * camera.height  # alpha and depth float32, ids int64
        keep = keep_surfaces and surface is not None and kept + size <= SURFACES_KEPT_BYTES
        if keep and same_camera(camera, view.camera):
            alpha, depth, ids = surface
            surfaces.append(RenderOutput(torch.empty(0), alpha, depth, ids=ids))
            kept += size
        else:
            surfaces.append(None)
    record_scores(task, preds, settings.metrics.resize, report, "coarse", voted, save_to)
    report.timings["label_render_ms_per_frame"] = 1000 * float(np.mean(seconds)) if seconds else 0
    return preds, surfaces


def same_camera(a: Camera, b: Camera) -> bool:
    """Whether two cameras draw the same pixels (size, intrinsics and pose)."""
    same_size = (a.width, a.height) == (b.width, b.height)
    return same_size and torch.equal(a.K, b.K) and torch.equal(a.world_to_cam, b.world_to_cam)


def record_eval_views(
    task: SceneTask,
    recorder: Recorder,
    preds: list[np.ndarray],
    report: SceneReport,
    gaussians: Gaussians,
    backend: str,
    diagnosis: SceneDiagnosis | None = None,
    background=(0.0, 0.0, 0.0),
    surfaces: list[RenderOutput | None] | None = None,
    rendered: list[np.ndarray] | None = None,  # T x [H, W, 3] uint8, Stage I's frames
) -> None:
    """Each eval view: with a diagnosis, its wrong pixels sorted by cause; with a recording,
    the render (on `background`, Stage I's colour, by `backend`), prediction, ground truth and
    causes at its nearest trajectory frame. The render is that frame's (`rendered`) where the
    frame's camera is the view's (a capture's photographs: the same pixels, not drawn again).
    The diagnosis reads the recorded render's ids, except on the compiled kernel, whose
    unshaded walk it reads: the view's label walk's (`surfaces`, from `score_views`) or, where
    none was kept, one it draws (the same bits, with a recording or without: a run that records
    nothing shades nothing)."""
    if not recorder.enabled and diagnosis is None:
        return
    ious = [r["iou"] for r in report.views[-len(preds) :]] if preds else []
    frames = nearest_frames(task)
    ids = diagnosis is not None and resolve_backend(backend, gaussians.device) != "native"
    for i, (view, pred) in enumerate(zip(task.eval_views, preds, strict=True)):
        at = frames[i]
        shared = recorder.enabled and rendered is not None
        drawn = rendered[at] if shared and same_camera(view.camera, task.trajectory[at]) else None
        whole = None
        if ids or (recorder.enabled and drawn is None):
            whole = eval_render(gaussians, view.camera, background, backend, ids)
        surface = whole if ids else (surfaces[i] if surfaces else None)
        causes = None if diagnosis is None else diagnosis.view(view, pred, surface)
        if recorder.enabled:
            recorder.eval_view(
                task.name,
                i,
                drawn if drawn is not None else to_uint8(whole.rgb),
                pred,
                view.gt,
                camera=view.camera,
                iou=ious[i],
                frame=frames[i],
                diagnosis=causes,
            )
    if diagnosis is not None:
        diagnosis.finish()


def eval_render(
    gaussians: Gaussians, camera: Camera, background, backend: str, ids: bool
) -> RenderOutput:
    """One eval view's render by `backend` (its colours as Stage I saw them), with the most
    visible Gaussian per pixel where `ids` asks: a backend that draws none (gsplat) leaves the
    ids to another (`render`'s choice) and keeps its own colours."""
    out = render(gaussians, camera, background=background, backend=backend, return_ids=ids)
    chosen = resolve_backend(backend, gaussians.device)
    if ids and capable_backend(chosen, {"return_ids": True}, gaussians.device) != chosen:
        out.rgb = render(gaussians, camera, background=background, backend=backend).rgb
    return out


def nearest_frames(task: SceneTask) -> list[int]:
    """For each eval view, the trajectory frame of the same name, else the nearest by camera
    centre (where the recording shows it on the `frame` timeline)."""
    index = {c.name: i for i, c in enumerate(task.trajectory)}
    centres = torch.stack([c.center for c in task.trajectory])
    return [
        index.get(v.name, int((centres - v.camera.center).norm(dim=1).argmin()))
        for v in task.eval_views
    ]
