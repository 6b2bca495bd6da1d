"""Consensus feedback: a video segmenter that cannot drift away for good.

While the trajectory is segmented, the masks accepted so far are voted into the Gaussians and
the fused labels are rendered into each next frame. Where the segmenter's own mask disagrees
with that render (foreground IoU below `min_iou`) or has lost the object, the segmenter is
re-prompted on that frame with the render as its mask prompt and the rest of the video in that
direction is segmented again from there. Works for any segmenter that takes mask prompts
(classical, SAM 2); the oracle reads the ground truth and needs none.

It is a mask policy of Stage I (`FeedbackPolicy`): the engine votes what it releases, under
the run's own frame selection, so a view the protocol holds out never votes. The render is
trusted once `min_frames` views have voted.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from sagonline.render.api import render_labels
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import VideoSegmenter, label_map
from sagonline.segment.prompts import ObjectPrompt, Prompt
from sagonline.vote.consensus import VoteAccumulator, VoteConfig


@dataclass
class FeedbackConfig:
    """Consensus feedback (`feedback=on`): the fused labels re-prompt a drifting segmenter."""

    enabled: bool = False
    """Off by default: the paper's protocol has no feedback."""
    every: int = 8
    """Frames segmented between two votes of what was accepted so far."""
    min_iou: float = 0.5
    """Re-prompt where the mask and the fused render agree less than this."""
    min_frames: int = 4
    """Masks voted before the fused render is trusted."""
    min_area: float = 0.002
    """The render must show this fraction of the frame as foreground."""
    max_restarts: int = 30
    """Re-prompts at most, per video."""


def foreground_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Mean IoU over the foreground labels present in either (H, W) label map (1 if none)."""
    labels = [k for k in np.union1d(np.unique(a), np.unique(b)) if k != 0]
    if not labels:
        return 1.0
    ious = []
    for k in labels:
        x, y = a == k, b == k
        ious.append(np.logical_and(x, y).sum() / max(np.logical_or(x, y).sum(), 1))
    return float(np.mean(ious))


def mask_prompt(labels: np.ndarray, frame: int) -> Prompt:
    """A prompt that marks every foreground label of `labels` by its mask on `frame`."""
    objects = [
        ObjectPrompt(label=int(k), mask=labels == k) for k in np.unique(labels) if int(k) != 0
    ]
    return Prompt(frame=frame, objects=objects)


@dataclass(frozen=True)
class FeedbackInputs:
    """What consensus feedback votes and renders with: its settings, the vote's, the scene,
    the trajectory's cameras, the label count, the label render's threshold, the vote's
    backend, and the longest side the fused labels are rendered at for a segmenter's advice
    (None: the view's; `FusedRender`). It is part of the masks' cache key: with feedback or
    advice, the masks depend on it."""

    config: FeedbackConfig
    vote: VoteConfig
    gaussians: Gaussians
    cameras: list[Camera]
    num_labels: int
    label_min_weight: float
    backend: str
    render_side: int | None = None


ADVICE_SIDE = 256
"""The advice's longer side at most (`advice_inputs`)."""


def advice_inputs(
    after: int,
    vote: VoteConfig,
    gaussians: Gaussians,
    cameras: list[Camera],
    num_labels: int,
    label_min_weight: float,
    backend: str,
) -> FeedbackInputs:
    """What Stage I's advice (`FusedRender`) renders with for a segmenter that asks for it
    once `after` views voted (`VideoSegmenter.wants_advice`): the fused labels, at
    `ADVICE_SIDE` at most."""
    config = FeedbackConfig(min_frames=after)
    return FeedbackInputs(
        config, vote, gaussians, list(cameras), num_labels, label_min_weight, backend, ADVICE_SIDE
    )


def enlarged(ids: np.ndarray, height: int, width: int) -> np.ndarray:  # [h, w] -> [H, W]
    """A label map enlarged, nearest: each pixel takes the source pixel its centre falls in.
    Rows, then columns: the same pixels as one 2D index (`np.ix_`), in a third of its time."""
    rows = (np.arange(height) + 0.5) * ids.shape[0] // height
    cols = (np.arange(width) + 0.5) * ids.shape[1] // width
    return ids.take(rows.astype(int), axis=0).take(cols.astype(int), axis=1)


class FusedRender:
    """The advice Stage I gives a segmenter that asks for it (`VideoSegmenter.wants_advice`):
    the labels fused from the views voted so far, the objects alone, rendered into the view
    it is about to segment ((H, W) ids, 0 elsewhere), or None before `after` views voted or
    while no Gaussian is an object.

    A view whose longer side exceeds `setup.render_side` is rendered with that side at
    `render_side` and enlarged to its size (nearest): the segmenter reads a box and an interior
    click from the advice, and a SAM-family decoder answers masks of 256 x 256 anyway."""

    def __init__(self, setup: FeedbackInputs, votes: VoteAccumulator, after: int):
        self.setup, self.votes, self.after = setup, votes, after
        self.renders, self.render_s = 0, 0.0

    def __call__(self, t: int) -> np.ndarray | None:
        if len(self.votes.frames) < self.after:
            return None
        start = time.perf_counter()
        labels = self.votes.labels()
        objects = torch.where(labels > 0, labels, -1)
        if not (objects >= 0).any():
            return None
        camera = self.setup.cameras[t]
        side = max(camera.width, camera.height)
        most = self.setup.render_side
        small = most is not None and side > most
        if small:
            s = most / side
            width, height = max(1, round(camera.width * s)), max(1, round(camera.height * s))
            camera = camera.scaled(width, height)
        out = render_labels(
            self.setup.gaussians,
            camera,
            objects,
            self.votes.k,
            min_weight=self.setup.label_min_weight,
            backend=self.setup.backend,
        )
        ids = out.cpu().numpy().astype(np.int64, copy=False)
        if small:
            full = self.setup.cameras[t]
            ids = enlarged(ids, full.height, full.width)
        self.renders += 1
        self.render_s += time.perf_counter() - start
        return ids


class FeedbackPolicy:
    """Which mask each view votes with, under consensus feedback: a mask policy of Stage I
    (`pipeline.stage_one.StageOne` calls `masks` and votes each mask it yields, if the view is
    one of the voting frames, before it asks for the next).

    Order: the prompt frame first; then forwards to the last frame, then backwards to the
    first, `every` frames at a time, each block checked against the vote of everything
    released before it. Where the fused labels' render and the segmenter's mask of a frame
    disagree (foreground IoU below `min_iou`), the segmenter is prompted again on that frame
    with the render and segments the rest of the video in that direction again.

    Why one class: the running vote (`votes`), the masks and the timers are shared by its three
    steps (fused render, re-segment, release); apart, they would pass all of them around."""

    def __init__(self, setup: FeedbackInputs):
        self.setup = setup
        self.stats: dict = {}

    def masks(
        self,
        segmenter: VideoSegmenter,
        frames: list[np.ndarray],
        prompt: Prompt,
        votes: VoteAccumulator,
        ground_truth: list[np.ndarray] | None = None,
    ) -> Iterator[tuple[int, np.ndarray, float]]:  # (frame, [H, W] `label_map`, seconds)
        """The masks the views vote with, one by one, in the feedback's order (see the class
        docstring); `votes` is the engine's running vote, read between two blocks."""
        cfg, start = self.setup.config, time.perf_counter()
        first = segmenter.segment(frames, prompt, ground_truth=ground_truth)
        masks, seconds = list(first.masks), list(first.seconds)
        n, p, step = len(frames), prompt.frame, max(cfg.every, 1)
        restarts: list[dict] = []
        render_s = 0.0

        def fused_render(t: int) -> np.ndarray:
            nonlocal render_s
            t0 = time.perf_counter()
            labels = votes.labels()
            objects = torch.where(labels > 0, labels, -1)  # the objects alone
            out = render_labels(
                self.setup.gaussians,
                self.setup.cameras[t],
                objects,
                votes.k,
                min_weight=self.setup.label_min_weight,
                backend=self.setup.backend,
            )
            render_s += time.perf_counter() - t0
            return out.cpu().numpy().astype(np.int64)

        def resegment(t: int, forward: bool, fused: np.ndarray) -> None:
            """Prompt the segmenter again on frame t with the fused render; on from there."""
            span = range(t, n) if forward else range(0, t + 1)
            sub = [frames[i] for i in span]
            sub_gt = [ground_truth[i] for i in span] if ground_truth is not None else None
            again = segmenter.segment(
                sub, mask_prompt(fused, 0 if forward else len(sub) - 1), ground_truth=sub_gt
            )
            for i, m, s in zip(span, again.masks, again.seconds, strict=True):
                masks[i], seconds[i] = m, seconds[i] + s
            masks[t] = fused  # the re-prompt itself is what the segmenter was told

        yield p, label_map(masks[p]), seconds[p]
        for forward in (True, False):
            order = list(range(p + 1, n)) if forward else list(range(p - 1, -1, -1))
            for b in range(0, len(order), step):
                block = order[b : b + step]
                if len(votes.frames) >= cfg.min_frames and len(restarts) < cfg.max_restarts:
                    for t in block:
                        fused = fused_render(t)
                        if (fused > 0).mean() < cfg.min_area:
                            continue  # the vote does not see the object here: nothing to tell
                        iou = foreground_iou(masks[t], fused)
                        if iou < cfg.min_iou:
                            restarts.append({"frame": t, "iou": iou})
                            resegment(t, forward, fused)
                            break  # the rest of the block was segmented again from t
                for t in block:
                    yield t, label_map(masks[t]), seconds[t]
        self.stats = {
            "restarts": len(restarts),
            "restarted_frames": [r["frame"] for r in restarts],
            "restart_ious": [round(r["iou"], 4) for r in restarts],
            "render_s": render_s,
            "total_s": time.perf_counter() - start,
        }


__all__ = [
    "FeedbackConfig",
    "FeedbackInputs",
    "FeedbackPolicy",
    "FusedRender",
    "foreground_iou",
    "mask_prompt",
]
