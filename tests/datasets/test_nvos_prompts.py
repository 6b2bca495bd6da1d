"""NVOS prompt protocols: a frozen points file (and its errors), SAGA's skeleton sampling
(seeded, reproducible), one click, and the protocol id each result carries."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sagonline.core.errors import DatasetError
from sagonline.datasets.nvos import NVOSDataset
from sagonline.datasets.nvos_prompts import SKELETON_KEEP, skeleton_points
from tests.datasets.test_datasets import _nvos


def _points_file(path, points: dict, scale=4):
    path.write_text(json.dumps({**points, "_scale": scale, "_comment": "test"}))
    return path


def test_frozen_points_land_on_the_reference_view(tmp_path):
    root, names, target, ref = _nvos(tmp_path)  # the views render at 32x24; masks are 32x24
    # points at the original resolution (4x the masks): (64, 44) -> (16, 11) in the view
    f = _points_file(tmp_path / "saga_v2_input_points.json", {"horns_center": [[64, 44], [70, 46]]})
    ds = NVOSDataset(root, tasks=["horns_center"], prompt="points", points_file=str(f))
    task = ds.load_scene("horns_center")
    obj = task.prompt.objects[0]
    assert task.prompt.frame == names.index(ref)
    np.testing.assert_allclose(obj.points, [[16, 11], [17.5, 11.5]])
    assert obj.point_labels.tolist() == [1, 1]
    assert task.meta["protocol"].startswith("nvos/points-saga_v2_input_points-")
    assert task.meta["protocol"].endswith("@2") and task.meta["protocol"] == ds.protocol


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not readable JSON"),
        ("[1, 2]", "must hold an object"),
        (json.dumps({"horns_center": [[1, 2]], "lego": [[1, 2]]}), r"unknown task\(s\) \['lego'\]"),
        (json.dumps({"horns_left": [[1, 2]]}), "no points for task 'horns_center'"),
        (json.dumps({"horns_center": [[1, 2, 3]]}), "task 'horns_center': expected"),
        (json.dumps({"horns_center": []}), "task 'horns_center': expected"),
        (json.dumps({"horns_center": [[1, 2]], "_scale": -1}), "_scale"),
    ],
)
def test_bad_points_files_name_the_file_and_task(tmp_path, content, message):
    root, *_ = _nvos(tmp_path)
    f = tmp_path / "points.json"
    f.write_text(content)
    with pytest.raises(DatasetError, match=message) as err:
        NVOSDataset(root, tasks=["horns_center"], prompt="points", points_file=str(f))
    assert "points.json" in str(err.value)


def test_points_outside_the_image_are_refused(tmp_path):
    root, *_ = _nvos(tmp_path)
    f = _points_file(tmp_path / "p.json", {"horns_center": [[10, 10], [500, 10]]})
    ds = NVOSDataset(root, tasks=["horns_center"], prompt="points", points_file=str(f))
    with pytest.raises(DatasetError, match=r"p\.json, task 'horns_center'.*\(500\.0, 10\.0\)"):
        ds.load_scene("horns_center")


def test_points_file_and_prompt_go_together(tmp_path):
    root, *_ = _nvos(tmp_path)
    with pytest.raises(DatasetError, match="points_file"):
        NVOSDataset(root, prompt="points")
    with pytest.raises(DatasetError, match="points_file"):
        NVOSDataset(root, prompt="scribbles", points_file="x.json")


def test_skeleton_sampling_is_sagas_rule_and_seeded():
    mask = np.zeros((40, 60), bool)
    mask[10:16, 5:55] = True  # a thick stroke: its skeleton is a line along row ~12
    a = skeleton_points(mask, np.random.default_rng(0), positive=True)
    b = skeleton_points(mask, np.random.default_rng(0), positive=True)
    c = skeleton_points(mask, np.random.default_rng(1), positive=True)
    np.testing.assert_array_equal(a, b)
    assert len(a) >= 1 and (a[:, 1] >= 11).all() and (a[:, 1] <= 14).all()
    assert not np.array_equal(a, c) or len(a) == 1
    # the rule by hand: skeleton pixels kept where a seeded uniform draw beats 0.98
    from skimage.morphology import skeletonize

    ys, xs = np.nonzero(skeletonize(mask))
    draw = np.random.default_rng(0).uniform(size=len(xs))
    keep = draw > SKELETON_KEEP[1]
    expected = np.stack([xs[keep], ys[keep]], 1) if keep.any() else None
    if expected is not None:
        np.testing.assert_array_equal(a, expected)


def test_protocols_click_and_skeleton_on_a_task(tmp_path):
    root, *_ = _nvos(tmp_path)
    click = NVOSDataset(root, tasks=["horns_center"], prompt="click")
    task = click.load_scene("horns_center")
    assert len(task.prompt.objects[0].points) == 1 and task.meta["protocol"] == "nvos/click@2"
    skel = NVOSDataset(root, tasks=["horns_center"], sampling="skeleton", seed=3)
    pts = skel.load_scene("horns_center").prompt.objects[0].points
    again = NVOSDataset(root, tasks=["horns_center"], sampling="skeleton", seed=3)
    np.testing.assert_array_equal(pts, again.load_scene("horns_center").prompt.objects[0].points)
    assert skel.protocol == "nvos/scribbles-skeleton@2"
    assert NVOSDataset(root).protocol == "nvos/scribbles-uniform16@2"
    assert NVOSDataset(root, prompt="clicks").protocol == "nvos/gt-clicks3@2"
