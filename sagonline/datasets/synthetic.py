"""The embedded default dataset: generated 2DGS scenes with 3D ground truth."""

from __future__ import annotations

import functools
import inspect
from dataclasses import replace

import numpy as np
import torch

from sagonline.datasets.base import DatasetAdapter, DatasetError, EvalView, SceneTask
from sagonline.datasets.common import click_prompt
from sagonline.render.api import render_labels
from sagonline.scene.generator import SEMANTIC_NAMES, SyntheticScene, make_scene


def gt_mask(
    scene: SyntheticScene,
    camera,
    labels: torch.Tensor,  # [N] every Gaussian's label
    num_labels: int,
) -> np.ndarray:
    """Ground truth of a view: per pixel, the label of largest composited weight (every
    Gaussian labelled, background 0 included); empty pixels are background. Rendered on the
    Gaussians' device by the fastest label walk there (the compiled kernel on the CPU)."""
    return (
        render_labels(
            scene.gaussians,
            camera.to(scene.gaussians.device),
            labels.to(scene.gaussians.device),
            num_labels,
            min_weight=1e-6,
            backend="auto",
        )
        .cpu()
        .numpy()
    )


def load_synthetic(
    *,
    preset: str = "cluttered_360",
    task: str = "instance",
    clicks: int = 3,
    seed: int = 0,
    device: str = "cpu",
    **settings: object,
) -> list[SceneTask]:
    """One generated scene as a task. task "instance" labels objects 1..K; "semantic" labels
    shapes by class (SEMANTIC_NAMES). scene: `make_scene`'s settings (layout, num_objects,
    num_gaussians, width, height, num_train_views, num_eval_views; its defaults otherwise)."""
    params = inspect.signature(make_scene).parameters
    settings = {k: v for k, v in settings.items() if k in params}
    layout = settings.get("layout", params["layout"].default)
    scene = make_scene(seed=seed, **settings)
    if task == "instance":
        labels, num_labels = scene.instance, scene.num_instances
        names = ["background"] + [f"{o.shape}_{i + 1}" for i, o in enumerate(scene.objects)]
    elif task == "semantic":
        labels, num_labels, names = scene.semantic, len(SEMANTIC_NAMES), list(SEMANTIC_NAMES)
    else:
        raise ValueError(f"synthetic task {task!r} is not 'instance' or 'semantic'")
    on_device = replace(scene, gaussians=scene.gaussians.to(device))
    traj_gt = [gt_mask(on_device, c, labels, num_labels) for c in scene.train_cameras]
    evals = [
        EvalView(c, gt_mask(on_device, c, labels, num_labels), c.name) for c in scene.eval_cameras
    ]
    prompt = click_prompt(traj_gt[0], 0, num_labels, clicks, seed)
    if task == "semantic":
        present = sorted({int(v) for v in np.unique(np.concatenate([g.ravel() for g in traj_gt]))})
        prompt.texts = [names[k] for k in range(1, num_labels)]
        prompt.objects = [o for o in prompt.objects if o.label in present]
    return [
        SceneTask(
            dataset="synthetic",
            name=preset,
            gaussians=scene.gaussians,
            trajectory=scene.train_cameras,
            eval_views=evals,
            num_labels=num_labels,
            prompt=prompt,
            trajectory_gt=traj_gt,
            gt_labels3d=labels,
            label_names=names,
            meta={"layout": layout, **scene.meta},
        )
    ]


class SyntheticDataset(DatasetAdapter):
    """Named presets of generated scenes; each preset is a dict of `load_synthetic` settings."""

    name = "synthetic"
    # 1 still: the truths are drawn at each view's size, so the resize rule that version 2
    # changed (datasets.base.PROTOCOL_VERSION) never reaches them
    protocol_version = 1

    def __init__(
        self, presets: dict[str, dict], scenes: list[str] | None = None, device: str = "cpu"
    ):
        self.presets = {k: dict(v) for k, v in presets.items()}
        self.device = device
        self.selected = list(scenes) if scenes else list(self.presets)
        unknown = [s for s in self.selected if s not in self.presets]
        if unknown:
            raise DatasetError(
                f"synthetic: unknown preset(s) {unknown}; known: {sorted(self.presets)}"
            )

    def scene_names(self) -> list[str]:
        return self.selected

    def load_scene(self, scene: str) -> SceneTask:
        settings = tuple(sorted({**self.presets[scene], "device": self.device}.items()))
        return _load_cached(scene, settings)

    @property
    def protocol(self) -> str:
        return f"synthetic/held-out-views@{self.protocol_version}"

    def describe(self) -> dict:
        return {
            "protocol_id": self.protocol,
            "protocol": "held-out views between the training views; trajectory = training "
            "views in orbit order",
            "presets": self.presets,
        }


@functools.lru_cache(maxsize=2)
def _load_cached(preset: str, settings: tuple) -> SceneTask:
    """Jobs of a sweep run in one process: generate each scene (and its ground truth) once."""
    return load_synthetic(preset=preset, **dict(settings))[0]
