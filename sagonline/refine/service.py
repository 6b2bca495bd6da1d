"""Answer label masks for any view, in whichever mode is ready.

Initial mode: the fused Stage I labels rendered at the view (available as soon as the vote is
done). Refined mode: the student's answer from the view's RGB render and its coarse label
render, once its background training has converged or spent its budget. Every answer says
which mode produced it and how long it took.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from sagonline.cameras import Camera
from sagonline.gaussians import Gaussians
from sagonline.refine.trainer import RefinementTrainer
from sagonline.render.api import render, render_labels, to_uint8


@dataclass
class Answer:
    mask: np.ndarray  # (H, W) int64 labels
    mode: str  # "initial" or "refined"
    ms: float


class OnlineSegmentation:
    def __init__(
        self,
        gaussians: Gaussians,
        labels: torch.Tensor,
        labelled: torch.Tensor,
        num_labels: int,
        trainer: RefinementTrainer | None = None,
        *,
        backend: str = "torch",
        min_weight: float = 0.2,
    ):
        self.g, self.labels, self.labelled = gaussians, labels, labelled
        self.num_labels, self.trainer = num_labels, trainer
        self.backend, self.min_weight = backend, min_weight

    @property
    def mode(self) -> str:
        return "refined" if self.trainer is not None and self.trainer.done.is_set() else "initial"

    def coarse(self, camera: Camera) -> np.ndarray:
        return (
            render_labels(
                self.g,
                camera,
                self.labels,
                self.num_labels,
                labelled=self.labelled,
                min_weight=self.min_weight,
                backend=self.backend,
            )
            .cpu()
            .numpy()
        )

    def answer(self, camera: Camera, mode: str | None = None) -> Answer:
        mode = mode or self.mode
        start = time.perf_counter()
        if mode == "initial":
            mask = self.coarse(camera)
        elif mode == "refined":
            if self.trainer is None:
                raise RuntimeError("no refinement student to answer in refined mode")
            rgb = to_uint8(render(self.g, camera, backend=self.backend).rgb)
            mask = self.trainer.predict(rgb, self.coarse(camera))
        else:
            raise ValueError(f"answer mode {mode!r} is not 'initial' or 'refined'")
        return Answer(mask=mask, mode=mode, ms=1000 * (time.perf_counter() - start))
