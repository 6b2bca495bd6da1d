"""2D mask metrics (IoU, pixel accuracy) and 3D label metrics.

Per view: IoU = TP / (TP + FP + FN) of each foreground label present in the ground truth or the
prediction, averaged over those labels (one binary foreground gives the usual IoU); accuracy =
(TP + TN) / all pixels, i.e. plain pixel accuracy over every label. A scene's mIoU / mAcc is
the mean over its views; a dataset's is the mean over scenes.

Resolution: the prediction is compared at the ground truth's resolution, resized with
nearest-neighbour (`resize="pred_to_gt"`, the default), or the ground truth at the
prediction's (`resize="gt_to_pred"`); nearest neighbour reads each target pixel's centre
(`nearest="centre"`, protocol 2) or, re-scoring a protocol 1 run, its top-left corner
(`nearest="corner"`; scene.io.images.NEAREST_SAMPLING).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from sagonline.scene.io.images import NEAREST_SAMPLING, resize_nearest

# the 3D metrics take tensors; the 2D scoring (`sagonline score`) needs no PyTorch
if TYPE_CHECKING:
    import torch

RESIZE_RULES = {
    "pred_to_gt": "prediction resized to the ground truth's resolution (nearest neighbour)",
    "gt_to_pred": "ground truth resized to the prediction's resolution (nearest neighbour)",
}


class ScoringError(ValueError):
    """A prediction that cannot be scored against its ground truth by the rules given."""


def align(
    pred, gt, resize: str | None = "pred_to_gt", nearest: str = "centre"
) -> tuple[np.ndarray, np.ndarray]:
    """The prediction and the ground truth at one resolution. resize None: the sizes must
    match. The aspect ratios must match always (a stretched prediction is not scored), and
    `gt_to_pred` never shrinks the ground truth to a smaller prediction (a 1x1 prediction would
    otherwise score a whole view)."""
    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.shape == gt.shape:
        return pred, gt
    (ph, pw), (gh, gw) = pred.shape[:2], gt.shape[:2]
    if resize is None:
        raise ScoringError(
            f"the prediction is {pw}x{ph} and the ground truth {gw}x{gh}; give a resize rule "
            f"({', '.join(sorted(RESIZE_RULES))}) to score them at one size"
        )
    if resize not in RESIZE_RULES:
        raise ScoringError(f"resize rule {resize!r} is not one of {sorted(RESIZE_RULES)}")
    if nearest not in NEAREST_SAMPLING:
        raise ScoringError(f"nearest {nearest!r} is not one of {sorted(NEAREST_SAMPLING)}")
    if abs(pw / ph - gw / gh) > 0.01 * (gw / gh):
        raise ScoringError(
            f"the prediction is {pw}x{ph} and the ground truth {gw}x{gh}: other aspect ratios "
            f"({pw / ph:.3f} and {gw / gh:.3f}); a stretched prediction is never scored"
        )
    if resize == "pred_to_gt":
        return resize_nearest(pred, gt.shape, nearest), gt
    if ph < gh or pw < gw:
        raise ScoringError(
            f"gt_to_pred with a prediction ({pw}x{ph}) smaller than the ground truth ({gw}x{gh})"
            " would score a shrunken truth; use pred_to_gt"
        )
    return pred, resize_nearest(gt, pred.shape, nearest)


def view_metrics(
    pred, gt, resize: str = "pred_to_gt", ignore: int | None = None, nearest: str = "centre"
) -> dict:
    """IoU (mean over foreground labels present) and pixel accuracy of one view.

    pred, gt: (H, W) integer label maps, 0 = background. `ignore`: a gt value to skip (e.g. 255).
    Returns {"iou", "acc", "per_label": {label: iou}}; iou is 1.0 when neither has foreground.
    A view whose every ground-truth pixel is ignored has nothing to score: iou and acc are None
    and "skipped" says why (it never counts as a perfect view).
    """
    p, g = align(pred, gt, resize, nearest)
    if ignore is not None:
        valid = g != ignore
        if not valid.any():
            return {"iou": None, "acc": None, "per_label": {}, "skipped": "every pixel is ignored"}
        if not valid.all():
            p, g = p[valid], g[valid]
    if p.size == 0:
        return {"iou": None, "acc": None, "per_label": {}, "skipped": "every pixel is ignored"}
    tp, predicted, true, correct = _label_counts(p.reshape(-1), g.reshape(-1))
    per_label = {}
    for lb in sorted(set(predicted) | set(true)):
        if lb != 0:
            t = tp.get(lb, 0)
            per_label[int(lb)] = t / (predicted.get(lb, 0) + true.get(lb, 0) - t)
    iou = float(np.mean(list(per_label.values()))) if per_label else 1.0
    acc = float(correct / max(p.size, 1))
    return {"iou": iou, "acc": acc, "per_label": per_label}


def _label_counts(p: np.ndarray, g: np.ndarray) -> tuple[dict, dict, dict, int]:
    """Per label: pixels both call it, pixels predicted it, pixels truly it (labels present
    only), and the pixels that agree. p, g: (P,) labels. One confusion matrix by bincount
    where both are small non-negative integers, else one `np.unique` of the pairs; exact
    counts either way."""
    integers = p.dtype.kind in "biu" and g.dtype.kind in "biu"
    lo, hi = min(p.min(), g.min()), max(p.max(), g.max())
    if integers and lo >= 0 and hi < 4096:
        k = int(hi) + 1
        pairs = g.astype(np.int64) * k + p.astype(np.int64)
        confusion = np.bincount(pairs, minlength=k * k).reshape(k, k)  # [truth, predicted]
        diag, rows, cols = np.diagonal(confusion), confusion.sum(1), confusion.sum(0)
        tp = {i: int(diag[i]) for i in np.flatnonzero(diag)}
        return tp, _nonzero(cols), _nonzero(rows), int(diag.sum())
    pairs, counts = np.unique(np.stack([g, p]), axis=1, return_counts=True)
    tp, predicted, true = {}, {}, {}
    for (t, q), c in zip(pairs.T.tolist(), counts.tolist(), strict=True):
        true[t] = true.get(t, 0) + c
        predicted[q] = predicted.get(q, 0) + c
        if t == q:
            tp[t] = c
    return tp, predicted, true, sum(tp.values())


def _nonzero(counts: np.ndarray) -> dict:
    return {int(i): int(counts[i]) for i in np.flatnonzero(counts)}


def labels3d_metrics(
    labels: torch.Tensor,  # [N] int64, -1 unlabelled
    gt: torch.Tensor,  # [N] long, the truth
    num_labels: int,
) -> dict:
    """3D label quality against per-Gaussian ground truth.

    accuracy: among labelled Gaussians, the fraction whose label equals the truth;
    coverage: fraction labelled; per-label IoU over Gaussians (labelled ones only count as
    predictions, unlabelled ones count as misses of their true label).
    """
    labels, gt = labels.cpu(), gt.cpu()
    labelled = labels >= 0
    correct = (labels == gt) & labelled
    out = {
        "accuracy": float(correct.sum() / labelled.sum().clamp_min(1)),
        "coverage": float(labelled.float().mean()),
        "accuracy_all": float(correct.float().mean()),
    }
    ious = {}
    for k in range(1, num_labels):
        pred_k = labelled & (labels == k)
        gt_k = gt == k
        union = (pred_k | gt_k).sum()
        if union > 0:
            ious[k] = float((pred_k & gt_k).sum() / union)
    out["miou"] = float(np.mean(list(ious.values()))) if ious else 1.0
    out["per_label_iou"] = ious
    return out


def match_labels(
    preds: list[np.ndarray],
    gts: list[np.ndarray],
    resize: str = "pred_to_gt",
    ignore: int | None = None,
) -> dict[int, int]:
    """One scene-wide mapping of predicted ids to ground-truth ids (Hungarian on IoU summed
    over all views), for automatic segmenters whose ids are arbitrary. Unmatched predicted
    ids map to fresh ids above every ground-truth id, so they still count as false positives.
    """
    from scipy.optimize import linear_sum_assignment

    pairs = [align(p, g, resize) for p, g in zip(preds, gts, strict=True)]
    if ignore is not None:  # void pixels take part in no match
        pairs = [(p[g != ignore], g[g != ignore]) for p, g in pairs]
    n_p = max(int(p.max(initial=0)) for p, _ in pairs) + 1
    n_g = max(int(g.max(initial=0)) for _, g in pairs) + 1
    conf = np.zeros((n_p, n_g), np.int64)
    for p, g in pairs:
        np.add.at(conf, (p.ravel(), g.ravel()), 1)
    inter = conf[1:, 1:].astype(np.float64)
    union = conf[1:].sum(1)[:, None] + conf[:, 1:].sum(0)[None, :] - inter
    iou = inter / np.maximum(union, 1)
    rows, cols = linear_sum_assignment(-iou)
    mapping = {0: 0}
    for r, c in zip(rows, cols, strict=True):
        if iou[r, c] > 0:
            mapping[r + 1] = c + 1
    fresh = n_g
    present = sorted({int(v) for p, _ in pairs for v in np.unique(p)})
    for p in present:
        if p not in mapping:
            mapping[p] = fresh
            fresh += 1
    return mapping


def relabel(mask: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    lut = np.arange(max(int(mask.max()) + 1, max(mapping) + 1))
    for a, b in mapping.items():
        lut[a] = b
    return lut[mask]


def match_and_relabel(
    preds: list[np.ndarray],
    gts: list[np.ndarray],
    resize: str = "pred_to_gt",
    ignore: int | None = None,
) -> list[np.ndarray]:
    """Predictions with their arbitrary ids mapped onto the ground truth's (`match_labels`)."""
    mapping = match_labels(preds, gts, resize, ignore)
    return [relabel(p, mapping) for p in preds]
