"""Answer label masks for any view, in the modes of the paper's Table II.

- coarse: the fused Stage I labels rendered at the view (ready as soon as the vote is done);
- initial: the view's RGB render answered by the 2D video segmenter (the paper's "instant
  response via the foundation model"; `sagonline.segment.novel_view`);
- refined: the student's answer from the view's RGB render and its coarse label render, once
  its background training has converged or spent its budget.
Every answer says which mode produced it and how long it took, render included.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from sagonline.refine.trainer import RefinementTrainer
from sagonline.render.api import render, render_labels, to_uint8
from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.novel_view import NovelViewSegmenter

MODES = ("coarse", "initial", "refined")


@dataclass
class Answer:
    mask: np.ndarray  # (H, W) int64 labels
    mode: str  # one of MODES
    ms: float


class OnlineSegmentation:
    """gaussians with their fused labels (N,) (-1: unlabelled); `trainer`: the student (refined
    mode); `segmenter`: the 2D segmenter for novel views (initial mode); `background`: the
    RGB renders' colour, the one Stage I's frames were rendered on (the student learnt from
    those, and the segmenter's prompts were set on them)."""

    def __init__(
        self,
        gaussians: Gaussians,
        labels: torch.Tensor,
        num_labels: int,
        trainer: RefinementTrainer | None = None,
        segmenter: NovelViewSegmenter | None = None,
        *,
        backend: str = "torch",
        min_weight: float = LABEL_MIN_WEIGHT,
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ):
        self.g, self.labels = gaussians, labels
        self.num_labels, self.trainer, self.segmenter = num_labels, trainer, segmenter
        self.backend, self.min_weight = backend, min_weight
        self.background = background

    @property
    def mode(self) -> str:
        """The best mode ready now: refined once the student is done, else initial where a
        segmenter answers, else coarse."""
        if self.trainer is not None and self.trainer.done.is_set():
            return "refined"
        return "initial" if self.segmenter is not None else "coarse"

    def coarse(self, camera: Camera) -> np.ndarray:
        return (
            render_labels(
                self.g,
                camera,
                self.labels,
                self.num_labels,
                min_weight=self.min_weight,
                backend=self.backend,
            )
            .cpu()
            .numpy()
        )

    def rgb(self, camera: Camera) -> np.ndarray:
        out = render(self.g, camera, background=self.background, backend=self.backend)
        return to_uint8(out.rgb)

    def answer(
        self,
        camera: Camera,
        mode: str | None = None,
        ground_truth: np.ndarray | None = None,
        size: tuple[int, int] | None = None,
    ) -> Answer:
        """The view's (H, W) labels in `mode` (None: `self.mode`); ground_truth is read by the
        oracle segmenter in initial mode only; `size`: (H', W') the student answers at in
        refined mode (its scores drawn up from the render's size; None: the camera's)."""
        mode = mode or self.mode
        start = time.perf_counter()
        if mode == "coarse":
            mask = self.coarse(camera)
        elif mode == "initial":
            if self.segmenter is None:
                raise RuntimeError("no 2D segmenter to answer in initial mode")
            mask = self.segmenter.answer(self.rgb(camera), camera, ground_truth)
        elif mode == "refined":
            if self.trainer is None:
                raise RuntimeError("no refinement student to answer in refined mode")
            mask = self.trainer.predict(self.rgb(camera), self.coarse(camera), size)
        else:
            raise ValueError(f"answer mode {mode!r} is not one of {', '.join(MODES)}")
        return Answer(mask=mask, mode=mode, ms=1000 * (time.perf_counter() - start))
