"""Synthetic scenes are deterministic and occluding; the oracle corrupts as specified."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.datasets.synthetic import load_synthetic
from sagonline.scene.generator import make_scene
from sagonline.segment import OracleSegmenter, Prompt


def test_same_seed_same_scene_other_seed_other_scene():
    a = make_scene(layout="360", num_gaussians=3000, seed=4)
    b = make_scene(layout="360", num_gaussians=3000, seed=4)
    c = make_scene(layout="360", num_gaussians=3000, seed=5)
    assert torch.equal(a.gaussians.means, b.gaussians.means)
    assert torch.equal(a.instance, b.instance)
    assert not torch.equal(
        a.gaussians.means[: len(c.gaussians)], c.gaussians.means[: len(a.gaussians)]
    )


@pytest.mark.parametrize("layout,objects", [("forward", 1), ("360", 5)])
def test_presets_shape(layout, objects):
    s = make_scene(
        layout=layout, num_gaussians=5000, num_train_views=10, num_eval_views=4, width=64, height=48
    )
    assert s.gaussians.kind == "2dgs"
    assert abs(len(s.gaussians) - 5000) < 600
    assert len(s.objects) == objects and int(s.instance.max()) == objects
    assert len(s.train_cameras) == 10 and len(s.eval_cameras) == 4
    assert {c.name for c in s.train_cameras}.isdisjoint(c.name for c in s.eval_cameras)
    assert len({o.shape for o in s.objects}) == objects  # different shapes


def test_too_few_gaussians_for_the_objects_is_said_by_name():
    with pytest.raises(ValueError, match=r"num_gaussians=200 is too few: its 5 object"):
        make_scene(layout="360", num_gaussians=200, width=32, height=24, num_train_views=2)
    assert len(make_scene(layout="360", num_gaussians=1000, width=32, height=24).gaussians)


def test_360_scene_has_occlusion():
    task = load_synthetic(
        layout="360", num_gaussians=8000, width=96, height=72, num_train_views=12, num_eval_views=2
    )[0]
    # every object is seen, and at least one is hidden in some view where others are visible
    visible = np.array(
        [[np.any(m == k) for k in range(1, task.num_labels)] for m in task.trajectory_gt]
    )
    assert visible.any(0).all()
    areas = np.array(
        [[np.count_nonzero(m == k) for k in range(1, task.num_labels)] for m in task.trajectory_gt]
    )
    assert (areas.max(0) > 2 * areas.min(0)).any()


def test_semantic_task_labels_shapes():
    task = load_synthetic(
        layout="360",
        task="semantic",
        num_gaussians=5000,
        width=64,
        height=48,
        num_train_views=6,
        num_eval_views=2,
    )[0]
    assert task.num_labels == 6 and task.label_names[0] == "background"
    assert task.prompt.texts == task.label_names[1:]


def _square(h=40, w=40, label=1):
    m = np.zeros((h, w), np.int64)
    m[10:30, 10:30] = label
    return m


def test_oracle_identity_and_corruptions():
    gts = [_square() for _ in range(40)]
    frames = [np.zeros((40, 40, 3), np.uint8)] * 40
    clean = OracleSegmenter().segment(frames, Prompt(), ground_truth=gts)
    assert all(np.array_equal(a, b) for a, b in zip(clean.masks, gts, strict=True))
    boundary = OracleSegmenter(boundary_px=3, seed=1).segment(frames, Prompt(), ground_truth=gts)
    diffs = [np.count_nonzero(a != b) for a, b in zip(boundary.masks, gts, strict=True)]
    assert min(diffs) > 0 and max(diffs) <= 4 * 26 * 3 + 100
    flicker = OracleSegmenter(flicker=0.5, seed=2).segment(frames, Prompt(), ground_truth=gts)
    emptied = sum(not m.any() for m in flicker.masks)
    assert 8 <= emptied <= 32
    drop = OracleSegmenter(drop=1.0).segment(frames, Prompt(), ground_truth=gts)
    assert not any(m.any() for m in drop.masks)
    again = OracleSegmenter(flicker=0.5, seed=2).segment(frames, Prompt(), ground_truth=gts)
    assert all(np.array_equal(a, b) for a, b in zip(again.masks, flicker.masks, strict=True))


def test_oracle_swaps_and_blobs():
    gt = _square()
    gt[0:8, 0:8] = 2
    frames = [np.zeros((40, 40, 3), np.uint8)]
    swapped = OracleSegmenter(swap=1.0).segment(frames, Prompt(), ground_truth=[gt]).masks[0]
    assert (swapped[gt == 1] == 2).all() and (swapped[gt == 2] == 1).all()
    blob = (
        OracleSegmenter(blob_rate=1.0, blob_radius=0.2, seed=3)
        .segment(frames, Prompt(), ground_truth=[_square()])
        .masks[0]
    )
    assert np.count_nonzero(blob != _square()) > 10


def test_oracle_needs_ground_truth():
    with pytest.raises(ValueError, match="ground truth"):
        OracleSegmenter().segment([np.zeros((4, 4, 3), np.uint8)], Prompt())
    with pytest.raises(ValueError, match="probability"):
        OracleSegmenter(flicker=2.0)


def test_corruptions_are_controlled_across_settings():
    """Each kind draws from its own stream: more flicker flickers a superset of the frames, and
    boundary noise does not change which frames flicker (a robustness table's rows differ
    only in what they name)."""
    from sagonline.segment.corruption import MaskCorruption

    gts = [_square() for _ in range(60)]

    def emptied(**kw):
        return {i for i, m in enumerate(MaskCorruption(seed=4, **kw).apply(gts, 2)) if not m.any()}

    low, high = emptied(flicker=0.1), emptied(flicker=0.3)
    assert low < high and high == emptied(flicker=0.3, boundary_px=3)
    with pytest.raises(ValueError, match="boundary_px"):
        MaskCorruption(boundary_px=-1)
