"""Segment a scene of one's own: prompts on one view -> one label per Gaussian.

The API behind `sagonline segment` (and the way to call it from a notebook):

    from sagonline.scene.io import read_scene
    from sagonline.scene.views import load_views
    from sagonline.pipeline.segment import segment_scene, clicks_prompt
    g = read_scene("point_cloud.ply")
    cams = load_views("sparse/0", g).cameras       # the numbering of `sagonline cameras`
    seg = segment_scene(g, cams, clicks_prompt(cams, 0, {"chair": [(412, 230)]}))
    seg.labels          # (N,) int64: -1 unlabelled, 0 background, 1.. the objects
    seg.names           # ["background", "chair"]

It drains Stage I's engine (`pipeline.stage_one.StageOne`: frames -> masks -> vote, each a
cached stage) on the cameras in the order given; with `cache_dir`, a rerun with other vote
settings reuses the frames and masks.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sagonline.core.errors import PromptError
from sagonline.core.machine import DEVICE_DEFAULT, resolve_device
from sagonline.core.provenance import digest_file
from sagonline.pipeline.events import StageOneBars
from sagonline.pipeline.graph import StageCache
from sagonline.pipeline.settings import RendererSettings
from sagonline.pipeline.stage_one import (
    PipelineSettings,
    StageOne,
    StageOneConfig,
)
from sagonline.pipeline.stages import SegmenterRun
from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import ObjectPrompt, Prompt
from sagonline.vote.consensus import VoteConfig, VoteResult


@dataclass
class Segmentation:
    """labels: (N,) int64, -1 for Gaussians the vote left unlabelled, else 0 (background) or
    1..K; names: K + 1 label names, background first; frames, masks: the trajectory's renders
    and the segmenter's (H, W) label maps; timings in seconds / ms."""

    labels: np.ndarray
    names: list[str]
    vote: VoteResult
    cameras: list[Camera]
    frames: list[np.ndarray]
    masks: list[np.ndarray]
    timings: dict = field(default_factory=dict)
    prompt_frame: int = 0

    @property
    def coverage(self) -> float:
        """The fraction of Gaussians the vote labelled (background included)."""
        return float((self.labels >= 0).mean()) if len(self.labels) else 0.0


def clicks_prompt(
    cameras: list[Camera],
    view: int,
    objects: dict[str, list[tuple[float, float]]],
    negatives: dict[str, list[tuple[float, float]]] | None = None,
) -> Prompt:
    """Clicks (x, y pixels of the view at its render size) per object name -> the prompt, its
    label names background first; objects are labelled 1.. in the order given."""
    negatives = negatives or {}
    unknown = sorted(set(negatives) - set(objects))
    if unknown:
        raise PromptError(
            f"negative clicks for unknown object(s) {unknown}; objects: {list(objects)}"
        )
    check_view(cameras, view)
    cam = cameras[view]
    prompts = []
    for label, (name, points) in enumerate(objects.items(), start=1):
        neg = negatives.get(name, [])
        pts = [*points, *neg]
        for x, y in pts:
            if not (0 <= x < cam.width and 0 <= y < cam.height):
                raise PromptError(
                    f"click ({x:g}, {y:g}) on view {view} ('{cam.name}') is outside its "
                    f"{cam.width}x{cam.height} render"
                )
        if not points:
            raise PromptError(f"object {name!r} has no positive click")
        prompts.append(
            ObjectPrompt(
                label=label,
                points=np.asarray(pts, np.float64).reshape(-1, 2),
                point_labels=np.array([1] * len(points) + [0] * len(neg), np.int64),
            )
        )
    return Prompt(frame=view, objects=prompts, names=["background", *objects])


def mask_prompt(
    cameras: list[Camera], view: int, mask: np.ndarray, names: list[str] | None = None
) -> Prompt:
    """A label map (0 background, 1..K objects) on one view -> the prompt with its label
    names. A 0/1 or 0/255 mask is one object."""
    check_view(cameras, view)
    cam, mask = cameras[view], np.asarray(mask)
    if mask.shape[:2] != (cam.height, cam.width):
        raise PromptError(
            f"mask is {mask.shape[1]}x{mask.shape[0]} but view {view} ('{cam.name}') renders at "
            f"{cam.width}x{cam.height}"
        )
    if mask.ndim == 3:
        mask = mask.max(axis=2)
    values = np.unique(mask)
    if set(values.tolist()) <= {0, 255} or set(values.tolist()) <= {0, 1}:
        mask = (mask > 0).astype(np.int64)
    ids = [int(k) for k in np.unique(mask) if k != 0]
    if not ids:
        raise PromptError(f"the mask on view {view} ('{cam.name}') marks no object")
    objects = [ObjectPrompt(label=k, mask=mask == k) for k in ids]
    names = names or ["background"] + [f"object_{k}" for k in range(1, max(ids) + 1)]
    return Prompt(frame=view, objects=objects, names=names)


def check_view(cameras: list[Camera], view: int) -> None:
    if not 0 <= view < len(cameras):
        raise PromptError(
            f"view {view} is out of range: there are {len(cameras)} views (0..{len(cameras) - 1})"
        )


def check_cameras_see_scene(gaussians: Gaussians, cameras: list[Camera]) -> None:
    """Stop when no Gaussian's centre is in front of and inside any camera: the camera file
    does not belong to this scene (another frame, another scale)."""
    means = gaussians.means.detach().float().cpu()
    seen = [int(cam.to("cpu").in_frame(means)[0].sum()) for cam in cameras]
    if not any(seen):
        raise PromptError(
            f"no Gaussian of the scene ({len(means)}) lies in front of and inside any of the "
            f"{len(cameras)} cameras: do the cameras belong to this scene (frame, scale)?"
        )


def plain_settings(obj) -> dict:
    """An object's plain attributes (numbers, strings, flags and lists of them): what a
    segmenter's masks depend on besides its weights."""
    plain = (bool, int, float, str, type(None))
    return {"class": type(obj).__name__} | {
        k: v
        for k, v in vars(obj).items()
        if not k.startswith("_")
        and (
            isinstance(v, plain)
            or (isinstance(v, (list, tuple)) and all(isinstance(x, plain) for x in v))
        )
    }


def segment_scene(
    gaussians: Gaussians,
    cameras: list[Camera],
    prompt: Prompt,
    *,
    segmenter: VideoSegmenter | SegmenterRun | None = None,
    vote: VoteConfig | None = None,
    backend: str = "auto",
    vote_backend: str = "auto",
    device: str = DEVICE_DEFAULT,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Segmentation:
    """Render `cameras` (in the order given), segment the video from `prompt` with `segmenter`
    (the weight-free classical one by default), vote the masks into one label per Gaussian:
    Stage I's engine (`pipeline.stage_one.StageOne`), drained, with progress said when asked
    (a bar on a terminal, a line every 15 s elsewhere). `background`: the render's colour (the
    one the scene was fitted on)."""
    names = list(prompt.names)
    if segmenter is None:
        from sagonline.segment.base import default_segmenter

        segmenter = default_segmenter()
    vote = vote or VoteConfig()
    check_view(cameras, prompt.frame)
    check_cameras_see_scene(gaussians, cameras)
    run = segmenter if isinstance(segmenter, SegmenterRun) else segmenter_run_of(segmenter)
    settings = PipelineSettings(
        RendererSettings(backend, vote_backend),
        device=device,
        progress=progress,
        background=tuple(background),
    )
    start = time.perf_counter()
    config = StageOneConfig(
        gaussians,
        list(cameras),
        run,
        vote,
        settings,
        max(prompt.num_labels, len(names)),
        cache=StageCache(cache_dir),
    )
    engine = StageOne(config, prompt)
    bars = StageOneBars(len(cameras), enabled=progress)
    for event in engine.stream():
        bars.update(event)
    bars.close()
    stage_one = engine.result()
    frames, seg, v = stage_one.frames.value, stage_one.masks.value, stage_one.vote.value
    warn_sparse_views(frames.images, cameras, settings.background)
    k = stage_one.num_labels
    names = list(names or ["background"]) + [f"object_{i}" for i in range(len(names or [1]), k)]
    timings = {
        "time_to_first_mask_s": frames.seconds_per_frame + seg.seconds[prompt.frame],
        "render_ms_per_frame": 1000 * frames.seconds_per_frame,
        "segment_ms_per_frame": seg.ms_per_frame,
        "vote_s": v.stats["aggregation_s"],
        "vote_ms_per_mask": v.stats["ms_per_mask"],
        "total_s": time.perf_counter() - start,
    }
    return Segmentation(
        stage_one.labels.astype(np.int64),
        names,
        v,
        list(cameras),
        frames.images,
        seg.masks,
        timings,
        prompt.frame,
    )


SPARSE_VIEW = 0.02  # a view whose render covers less than this share of its pixels


def sparse_views(
    frames: list[np.ndarray],  # [H, W, 3] uint8 renders
    background: tuple[float, float, float],  # the render background in [0, 1]
) -> list[int]:
    """The views whose render differs from the background on less than SPARSE_VIEW of its
    pixels: they show almost nothing of the scene."""
    bg = np.round(255 * np.asarray(background, np.float32)).astype(np.int16)
    return [
        i
        for i, f in enumerate(frames)
        if (np.abs(f.astype(np.int16) - bg).max(axis=-1) > 2).mean() < SPARSE_VIEW
    ]


def warn_sparse_views(frames, cameras: list[Camera], background) -> None:
    """Say which views show almost nothing (a camera file of another scene, an orbit framed on
    outliers): their masks carry little, and an object segmented from them means little."""
    sparse = sparse_views(frames, background)
    if sparse:
        shown = ", ".join(f"{i} ('{cameras[i].name}')" for i in sparse[:8])
        more = f" and {len(sparse) - 8} more" if len(sparse) > 8 else ""
        warnings.warn(
            f"{len(sparse)} of {len(frames)} views show almost nothing of the scene (under "
            f"{SPARSE_VIEW:.0%} of their pixels): {shown}{more}; check the cameras or the orbit",
            stacklevel=3,
        )


def segmenter_run_of(segmenter: VideoSegmenter) -> SegmenterRun:
    """A segmenter built in code (not from a config node): what its masks depend on are its
    plain attributes and the digests of its weight files."""
    weights = {f: digest_file(f) for f in segmenter.weight_files()}
    return SegmenterRun(segmenter, plain_settings(segmenter), weights)


def check_click_on_scene(
    alpha: np.ndarray,  # [H, W] the view's accumulated opacity
    cam: Camera,
    view: int,
    x: float,
    y: float,
    name: str,
    hint: str = "the view panel",
) -> None:
    """Refuse a positive click where nothing of the scene is drawn (a click on the background
    of an object scan, or on empty sky): it would select nothing."""
    a = float(alpha[min(int(y), cam.height - 1), min(int(x), cam.width - 1)])
    if a < 0.5:
        raise PromptError(
            f"a click on {name!r} at ({x:g}, {y:g}) of view {view} ('{cam.name}') lands where no "
            f"Gaussian is drawn (opacity {a:.2f}): click on the object ({hint} shows the view)"
        )


def check_objects_were_found(seg) -> None:
    """Refuse to write an object that selected no Gaussian (an empty PLY and exit 0 would say
    it worked)."""
    for k, name in enumerate(seg.names):
        if k == 0:
            continue
        count = int((seg.labels == k).sum())
        if count == 0:
            seen = sum(int((m == k).any()) for m in seg.masks)
            raise PromptError(
                f"object {name!r} selected no Gaussian (the 2D segmenter marked it in {seen} of "
                f"{len(seg.masks)} views, and no Gaussian's votes made it {name!r}); nothing was "
                "written: give another click, a mask, or another segmenter"
            )


def write_segment_folder(
    out: Path,
    gaussians: Gaussians,
    seg: Segmentation,
    scene: Path | None,
    info: dict,
    *,
    backend: str = "auto",
    device: str = DEVICE_DEFAULT,
    record: bool = True,
    overwrite: bool = False,
    inputs=(),
    progress=None,
    min_weight: float = LABEL_MIN_WEIGHT,
) -> Path:
    """The segment folder (`sagonline.labels.export.write_segmentation`): label renders of every
    trajectory view, labels, object PLYs and the recording; what `sagonline segment` and the
    viewer's Export both write. progress(items, what) wraps the label renders (a bar);
    min_weight: a pixel of a label render takes a label where that label's Gaussians make up
    this much of it (`render_labels`; recorded in labels.json as label_render.min_weight)."""
    import torch

    from sagonline.labels.export import write_segmentation
    from sagonline.record.segmentation import record_segmentation
    from sagonline.render.api import render_labels

    labels = torch.from_numpy(seg.labels)
    device = resolve_device(device)
    g = gaussians.to(device)
    pairs = list(zip(seg.cameras, seg.frames, strict=True))
    views = []
    for cam, frame in progress(pairs, "label renders") if progress else pairs:
        lab = render_labels(
            g, cam.to(device), labels, len(seg.names), backend=backend, min_weight=min_weight
        )
        views.append((cam.name, frame, lab.cpu().numpy()))

    def write_recording(path: Path) -> None:
        record_segmentation(
            path,
            gaussians,
            seg.labels,
            seg.names,
            seg.cameras,
            seg.frames,
            seg.masks,
            [v[2] for v in views],
            info["prompt"],
            seg.prompt_frame,
        )

    info = info | {"label_render": {"min_weight": float(min_weight)}}
    return write_segmentation(
        out,
        gaussians,
        seg.labels,
        seg.names,
        source=scene,
        info=info,
        views=views,
        record=write_recording if record else None,
        overwrite=overwrite,
        inputs=inputs,
        command="segment",
    )
