"""Where a scored view's missed pixels are lost: the fit, the vote, or the 2D segmenter.

For every pixel of an eval view that the label render gets wrong, the Gaussian that shows it
(the one of largest blend weight, `render(..., return_ids=True)`) is asked why:

missed (ground truth object k, predicted something else):
- `fit_empty`: nothing opaque is rendered there (alpha < 0.5): the fit has no surface where the
  object is;
- `fit_covered`: the Gaussian shown is labelled another label by the vote, and the truth's own
  masks, voting on the same views by the same rule, would label it so too: it is not part of the
  object (a floater or background surfel in front of it, or the object's surface lies elsewhere);
- `segmenter`: the Gaussian is labelled another label, but the truth's masks would label it k:
  the 2D masks outvoted the truth;
- `vote_unseen`: the Gaussian got no vote (no voting view saw it within eps and delta);
- `vote_few`: fewer votes than `min_votes`;
- `vote_ambiguous`: its top two labels were within `margin` of each other (or tied);
- `label_render`: the Gaussian shown is labelled k, yet the pixel's label blend (other labelled
  Gaussians behind or beside it, or less than `min_weight` in all) gave another label.
extra (ground truth background, predicted an object): `extra_fit` where the truth's masks also
label the Gaussian shown as that object (its surface reaches beyond the object's silhouette),
`extra_segmenter` where they do not, `extra_render` where the Gaussian shown is not that object.

Without the trajectory's ground truth (no counterfactual vote), `fit_covered` and `segmenter`
are reported together as `outvoted`. Counts are pixels at the render's resolution (the ground
truth resized to it by nearest neighbour).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sagonline.cameras import Camera
from sagonline.consensus import VoteConfig, VoteResult
from sagonline.gaussians import Gaussians
from sagonline.io.images import resize_nearest

MISSED = (
    "fit_empty",
    "fit_covered",
    "segmenter",
    "outvoted",
    "vote_unseen",
    "vote_few",
    "vote_ambiguous",
    "label_render",
)
EXTRA = ("extra_fit", "extra_segmenter", "extra_render")
CAUSE_GROUPS = {
    "fit": ("fit_empty", "fit_covered"),
    "vote": ("vote_unseen", "vote_few", "vote_ambiguous", "label_render", "outvoted"),
    "segmenter": ("segmenter",),
}
# Colours of the causes in the recording's diagnosis image (RGB).
CAUSE_COLOURS = {
    "fit_empty": (255, 40, 40),
    "fit_covered": (255, 140, 0),
    "segmenter": (170, 60, 255),
    "outvoted": (200, 120, 200),
    "vote_unseen": (40, 120, 255),
    "vote_few": (0, 200, 255),
    "vote_ambiguous": (255, 230, 0),
    "label_render": (120, 255, 120),
    "extra_fit": (120, 0, 0),
    "extra_segmenter": (80, 0, 120),
    "extra_render": (0, 90, 0),
}


@dataclass
class GaussianCauses:
    """Per Gaussian (N,): its state in the run's vote and, where known, in the truth's vote."""

    labels: torch.Tensor  # (N,) long, the run's label (meaningful where labelled)
    labelled: torch.Tensor  # (N,) bool
    votes: torch.Tensor  # (N,) float, votes cast for it
    ambiguous: torch.Tensor  # (N,) bool, voted enough but within the margin (or tied)
    truth: torch.Tensor | None  # (N,) long label by the truth's masks (-1 unlabelled), or None

    @classmethod
    def of(cls, run: VoteResult, cfg: VoteConfig, truth: VoteResult | None) -> GaussianCauses:
        votes = run.histogram.sum(1).cpu()
        enough = votes >= max(cfg.min_votes, 1)
        labelled = run.labelled.cpu()
        truth_labels = None
        if truth is not None:
            truth_labels = torch.where(truth.labelled, truth.labels, -1).cpu()
        return cls(run.labels.cpu(), labelled, votes, enough & ~labelled, truth_labels)


def diagnose_view(
    gaussians: Gaussians,
    camera: Camera,
    gt: np.ndarray,
    pred: np.ndarray,
    causes: GaussianCauses,
    *,
    ignore: int | None = None,
    backend: str = "auto",
) -> tuple[dict[str, int], np.ndarray]:
    """Counts of one view's wrong pixels by cause, and an (H, W) uint8 map of the causes
    (index into MISSED + EXTRA, +1; 0: right). gt: the view's ground truth (any resolution of
    the camera's aspect); pred: the label render at the camera's size."""
    from sagonline.render.api import render

    h, w = camera.height, camera.width
    truth = resize_nearest(np.asarray(gt), (h, w)).astype(np.int64)
    pred = resize_nearest(np.asarray(pred), (h, w)).astype(np.int64)
    out = render(gaussians, camera, backend=backend, return_ids=True)
    alpha = out.alpha.detach().cpu().numpy()
    ids = out.ids.cpu().numpy().astype(np.int64)
    valid = np.ones_like(truth, bool) if ignore is None else truth != ignore
    missed = valid & (truth > 0) & (pred != truth)
    extra = valid & (truth == 0) & (pred > 0)
    g = np.clip(ids, 0, None)
    shown = ids >= 0
    run_label = causes.labels.numpy()[g]
    labelled = causes.labelled.numpy()[g] & shown
    votes = causes.votes.numpy()[g]
    ambiguous = causes.ambiguous.numpy()[g]
    kinds = np.zeros((h, w), np.uint8)

    def mark(name: str, where: np.ndarray) -> None:
        kinds[where & (kinds == 0)] = (MISSED + EXTRA).index(name) + 1

    empty = missed & ((alpha < 0.5) | ~shown)
    mark("fit_empty", empty)
    same = labelled & (run_label == truth)
    mark("label_render", missed & same)
    other = missed & labelled & (run_label != truth)
    if causes.truth is not None:
        truth_label = causes.truth.numpy()[g]
        mark("segmenter", other & (truth_label == truth))
        mark("fit_covered", other)
    else:
        mark("outvoted", other)
    unlabelled = missed & ~labelled
    mark("vote_unseen", unlabelled & (votes == 0))
    mark("vote_few", unlabelled & (votes > 0) & ~ambiguous)
    mark("vote_ambiguous", unlabelled)
    shows_it = labelled & (run_label == pred)
    if causes.truth is not None:
        truth_label = causes.truth.numpy()[g]
        mark("extra_fit", extra & shows_it & (truth_label == pred))
        mark("extra_segmenter", extra & shows_it)
    else:
        mark("extra_segmenter", extra & shows_it)
    mark("extra_render", extra)
    counts = {name: int((kinds == i + 1).sum()) for i, name in enumerate(MISSED + EXTRA)}
    counts["missed_px"] = int(missed.sum())
    counts["extra_px"] = int(extra.sum())
    counts["object_px"] = int((valid & (truth > 0)).sum())
    return counts, kinds


def shares(rows: list[dict]) -> dict[str, float | None]:
    """Over several views' counts: each cause group's share of the missed pixels (fit, vote,
    segmenter) and each cause's; None where nothing was missed."""
    missed = sum(r.get("missed_px", 0) for r in rows)
    out: dict[str, float | None] = {"missed_px": missed}
    for group, names in CAUSE_GROUPS.items():
        n = sum(r.get(name, 0) for r in rows for name in names)
        out[f"share_{group}"] = n / missed if missed else None
    for name in MISSED:
        n = sum(r.get(name, 0) for r in rows)
        out[f"share_{name}"] = n / missed if missed else None
    return out


def cause_image(kinds: np.ndarray) -> np.ndarray:
    """(H, W) cause map -> (H, W, 3) uint8 colours (black where right)."""
    colours = np.zeros((len(MISSED + EXTRA) + 1, 3), np.uint8)
    for i, name in enumerate(MISSED + EXTRA):
        colours[i + 1] = CAUSE_COLOURS[name]
    return colours[kinds]


__all__ = ["CAUSE_GROUPS", "EXTRA", "MISSED", "GaussianCauses", "diagnose_view", "shares"]
