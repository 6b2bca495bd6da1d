"""The common currency of every dataset: a `SceneTask` (what to segment, where to score)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from sagonline.core.errors import DatasetError
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.prompts import Prompt

__all__ = ["PROTOCOL_VERSION", "DatasetAdapter", "DatasetError", "EvalView", "SceneTask"]

# The version every protocol id ends with where the ground truth can be resized (`@2`): 2 since
# truths, prompt masks and predictions are resized pixel-centred (scene.io.images.resize_nearest);
# 1 read each target pixel's top-left source pixel, half a pixel off. The synthetic scenes'
# truths are drawn at the view's size, never resized: their protocol stays at 1.
# docs/datasets.md, "Protocol versions".
PROTOCOL_VERSION = 2


@dataclass
class EvalView:
    """A scored view: its camera and (H_gt, W_gt) ground-truth label map (0 = background);
    `group`: which of the task's `view_groups` it belongs to (None: no grouping); `meta`:
    per-view facts copied into its per_view.csv row (e.g. the angle to the nearest photograph)."""

    camera: Camera
    gt: np.ndarray
    name: str
    group: str | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.gt = read_only(self.gt)


def read_only(mask: np.ndarray) -> np.ndarray:
    """The ground truth as a read-only array: it is never changed in place, so its content
    digest is computed once per run (`core.provenance.digest_arrays`)."""
    mask = np.asarray(mask)
    mask.setflags(write=False)
    return mask


@dataclass
class SceneTask:
    """One scene of one protocol.

    trajectory: the T views the 2D segmenter watches, in video order; trajectory_gt: their
    ground-truth label maps where the dataset has them (the oracle and `segmenter_miou` use
    them); eval_views: where the fused labels are scored; num_labels: label count including
    background; gt_labels3d: (N,) per-Gaussian truth where known (synthetic scenes);
    ignore_label: a ground-truth value that is never scored (e.g. 255 for void pixels);
    view_groups: the groups the eval views are sorted into (each group's mIoU is reported);
    background: the RGB colour in [0, 1] the scene was fitted on, which its renders use (None:
    the pipeline's, black).
    """

    dataset: str
    name: str
    gaussians: Gaussians
    trajectory: list[Camera]
    eval_views: list[EvalView]
    num_labels: int
    prompt: Prompt
    trajectory_gt: list[np.ndarray] | None = None
    gt_labels3d: torch.Tensor | None = None
    label_names: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    ignore_label: int | None = None
    view_groups: list[str] = field(default_factory=list)
    background: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.trajectory_gt is not None:
            self.trajectory_gt = [read_only(m) for m in self.trajectory_gt]


class DatasetAdapter:
    """A dataset: a list of scene names and a loader per scene. Subclasses set `name` and
    override both methods; a scene that cannot load raises `DatasetError`."""

    name = "dataset"
    protocol_version = PROTOCOL_VERSION  # what its protocol ids end with (`@<version>`)

    def scene_names(self) -> list[str]:
        raise NotImplementedError

    def load_scene(self, scene: str) -> SceneTask:
        raise NotImplementedError

    @property
    def protocol(self) -> str:
        """A short versioned id of the evaluation protocol (`<dataset>/<variant>@<version>`):
        every result carries it, and no table averages results of different ids. Adapters
        whose settings change what is scored or how it is prompted name the variant."""
        return f"{self.name}/default@{self.protocol_version}"

    def describe(self) -> dict:
        """Protocol settings recorded in every report."""
        return {}
