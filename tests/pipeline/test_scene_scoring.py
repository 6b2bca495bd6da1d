"""A scene's scoring: the ignore label reaches it; empty ground truth fails it, with a hint."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from bench.runners.eval import evaluate
from sagonline.pipeline import (
    SceneReport,
    record_scores,
)
from sagonline.scene.io.cameras import load_cameras
from tests.fixtures import (
    llff_scene,
    object_mask,
    write_image,
)
from tests.refusals import NAMES, generic_cfg


def test_ignore_label_reaches_scoring(tiny_task):
    view = tiny_task.eval_views[0]
    gt = view.gt.copy()
    gt[0, 0] = 255
    task = dataclasses.replace(
        tiny_task, eval_views=[dataclasses.replace(view, gt=gt)], ignore_label=255
    )
    report = SceneReport(scene="s")
    miou, _ = record_scores(task, [view.gt], "pred_to_gt", report, "coarse")
    assert miou == pytest.approx(1.0)  # was 0.5: the void pixel counted as a missed label


def test_empty_ground_truth_fails_the_scene_with_a_hint(tmp_path):
    root = tmp_path / "data"
    llff_scene(root / "cap", NAMES)
    for name in NAMES:
        write_image(root / "cap" / "masks" / f"{name}.png", np.zeros((24, 32), np.uint8))
    cfg = generic_cfg(root, "record=false")
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg, tmp_path / "run")
    assert exc.value.code == 1
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["status"] == "failed"
    assert "mask_threshold=0" in saved["scenes"][0]["error"]
    # a failed run does not block its rerun once the data is fixed
    _, sc = llff_scene(root / "cap", NAMES)
    for cam, name in zip(load_cameras(root / "cap"), NAMES, strict=True):
        mask = (object_mask(sc, cam) > 0).astype(np.uint8) * 255
        write_image(root / "cap" / "masks" / f"{name}.png", mask)
    assert evaluate(cfg, tmp_path / "run")["status"] == "complete"
