"""Metrics against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.score.metrics import labels3d_metrics, view_metrics


def test_binary_iou_and_accuracy_by_hand():
    gt = np.array([[0, 1, 1, 0], [0, 1, 1, 0]])
    pred = np.array([[0, 1, 0, 0], [1, 1, 1, 0]])
    # TP = 3, FP = 1, FN = 1, TN = 3
    m = view_metrics(pred, gt)
    assert m["iou"] == pytest.approx(3 / 5)
    assert m["acc"] == pytest.approx(6 / 8)


def test_multilabel_mean_over_present_labels():
    gt = np.array([[1, 1, 2, 2]])
    pred = np.array([[1, 2, 2, 3]])
    m = view_metrics(pred, gt)
    assert m["per_label"] == {1: pytest.approx(1 / 2), 2: pytest.approx(1 / 3), 3: 0.0}
    assert m["iou"] == pytest.approx((1 / 2 + 1 / 3 + 0) / 3)
    assert m["acc"] == pytest.approx(2 / 4)


def test_empty_foreground_is_perfect():
    assert view_metrics(np.zeros((3, 3)), np.zeros((3, 3)))["iou"] == 1.0


def test_resize_rules():
    gt = np.zeros((4, 4), int)
    gt[:2, :2] = 1
    pred_small = np.array([[1, 0], [0, 0]])
    assert view_metrics(pred_small, gt, "pred_to_gt")["iou"] == 1.0
    pred_large = np.kron(gt, np.ones((2, 2), int))
    assert view_metrics(pred_large, gt, "gt_to_pred")["iou"] == 1.0
    with pytest.raises(ValueError, match="smaller than the ground truth"):
        view_metrics(pred_small, gt, "gt_to_pred")  # never a shrunken truth
    with pytest.raises(ValueError, match="resize rule"):
        view_metrics(pred_small, gt, "bilinear")
    with pytest.raises(ValueError, match="give a resize rule"):
        view_metrics(pred_small, gt, None)


def test_labels3d_metrics():
    gt = torch.tensor([1, 1, 2, 0, 0])
    labels = torch.tensor([1, 2, 2, 0, -1])  # -1: unlabelled
    m = labels3d_metrics(labels, gt, 3)
    assert m["accuracy"] == pytest.approx(3 / 4)
    assert m["coverage"] == pytest.approx(4 / 5)
    assert m["per_label_iou"] == {1: pytest.approx(1 / 2), 2: pytest.approx(1 / 2)}


@pytest.mark.parametrize("labels", [(0, 3), (0, 300), (-1, 5000)])
@pytest.mark.parametrize("ignore", [None, 255])
def test_view_metrics_counts_every_label_exactly(labels, ignore):
    """The confusion-matrix counts (small labels) and the pairs' counts (negative or large
    labels, float predictions) equal a count per label by comparison."""
    rng = np.random.default_rng(labels[1])
    gt = rng.integers(*labels, (23, 31))
    gt[rng.random(gt.shape) < 0.2] = 255
    for pred in (rng.integers(*labels, gt.shape), rng.integers(*labels, gt.shape).astype(float)):
        m = view_metrics(pred, gt, ignore=ignore)
        keep = np.ones(gt.shape, bool) if ignore is None else gt != ignore
        p, g = pred[keep], gt[keep]
        expected = {}
        for lb in sorted((set(p.tolist()) | set(g.tolist())) - {0}):
            tp = np.count_nonzero((p == lb) & (g == lb))
            expected[int(lb)] = tp / np.count_nonzero((p == lb) | (g == lb))
        assert m["per_label"] == pytest.approx(expected)
        assert m["acc"] == pytest.approx(np.count_nonzero(p == g) / p.size)
