"""The scored label renders' size (`label_render.size`): the eval view's camera, resized to the
ground truth by the metrics' rule, or that camera rescaled to the ground truth's own size."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.runners.eval import evaluate
from sagonline.pipeline import PipelineSettings
from sagonline.pipeline.settings import LabelRenderSettings
from sagonline.render.api import render_labels
from tests.fixtures import compose_config, llff_scene, object_mask, write_image

NAMES = [f"IMG_{i:04d}" for i in range(5)]


def test_the_scored_camera_is_the_views_or_rescaled_to_its_truth(tiny_task):
    view = tiny_task.eval_views[0]
    assert PipelineSettings().scored_camera(view) is view.camera
    view = type(view)(view.camera, np.zeros((60, 80), np.uint8), view.name)
    cam = PipelineSettings(label_render=LabelRenderSettings(size="truth")).scored_camera(view)
    assert (cam.width, cam.height) == (80, 60)
    assert cam.K[0, 0] == pytest.approx(2 * float(view.camera.K[0, 0]))
    assert cam.K[1, 2] == pytest.approx(2 * float(view.camera.K[1, 2]))
    assert cam.world_to_cam is view.camera.world_to_cam
    # the same view at the larger size: its labels cover the same part of the frame
    labels = (tiny_task.gaussians.means[:, 0] > 0).long()
    small = render_labels(tiny_task.gaussians, view.camera, labels, 2).numpy()
    large = render_labels(tiny_task.gaussians, cam, labels, 2).numpy()
    assert abs(large.mean() - small.mean()) < 0.1


def test_a_size_that_is_not_one_is_refused():
    with pytest.raises(ValueError, match="label_render.size"):
        LabelRenderSettings(size="full")


def _capture(root: Path) -> None:
    """A generic capture whose masks are 48x36 (the renders at 24x18 by render_max_side)."""
    cams, scene = llff_scene(root / "cap", NAMES, width=48, height=36)
    for cam, name in zip(cams, NAMES, strict=True):
        mask = (object_mask(scene, cam) > 0).astype(np.uint8) * 255
        write_image(root / "cap" / "masks" / f"{name}.png", mask)


def test_labels_scored_at_the_truths_size(tmp_path, capsys):
    root = tmp_path / "data"
    _capture(root)
    runs = {}
    for size in ("render", "truth"):
        cfg = compose_config(
            "eval",
            "dataset=generic",
            f"dataset.root={root}",
            "dataset.adapter.render_max_side=24",
            f"label_render.size={size}",
            "progress=false",
            "record=false",
            f"cache_dir={tmp_path / 'cache'}",
        )
        runs[size] = evaluate(cfg, tmp_path / size)
    shapes = {
        size: {cv2.imread(str(p), cv2.IMREAD_UNCHANGED).shape for p in run.glob("**/*.png")}
        for size, run in ((s, tmp_path / s / "predictions") for s in runs)
    }
    assert shapes == {"render": {(18, 24)}, "truth": {(36, 48)}}
    # one vote (the stages are shared), two renders of its labels: the scores differ only there
    assert runs["truth"]["scenes"][0]["stages"]["vote"] == "cached"
    assert "ground truth's resolution (label_render.size=truth)" in runs["truth"]["resize_rule"]
    written = json.loads((tmp_path / "truth" / "metrics.json").read_text())
    assert written["config"]["label_render"]["size"] == "truth"
    for run in runs.values():
        assert 0.5 < run["miou"] <= 1
    # a run whose recorded label size is not one is refused by name when read back (export)
    from sagonline.apps.cli import main

    written["config"]["label_render"]["size"] = "full"
    (tmp_path / "truth" / "metrics.json").write_text(json.dumps(written))
    assert main(["export", str(tmp_path / "truth")]) == 2
    err = capsys.readouterr().err
    assert "config.label_render" in err and "full" in err, err


def test_the_students_answers_are_drawn_at_the_truths_size_too(tmp_path):
    """With `label_render.size=truth` the student answers at the masks' size (its class scores
    drawn up from the render's), as the coarse labels it is compared with are drawn."""
    root = tmp_path / "data"
    _capture(root)
    cfg = compose_config(
        "eval",
        "dataset=generic",
        f"dataset.root={root}",
        "dataset.adapter.render_max_side=24",
        "label_render.size=truth",
        "refine=student",
        "refine.max_steps=2",
        "refine.batch_size=2",
        "progress=false",
        "record=false",
        f"cache_dir={tmp_path / 'cache'}",
    )
    run = evaluate(cfg, tmp_path / "run")
    refined = list((tmp_path / "run" / "predictions_refined").glob("**/*.png"))
    assert refined and {cv2.imread(str(p), cv2.IMREAD_UNCHANGED).shape for p in refined} == {
        (36, 48)
    }
    assert 0 < run["refined_miou"] <= 1
