"""Where a scored view's missed pixels are lost: the fit, the vote, or the 2D segmenter.

For every pixel of an eval view that the label render gets wrong, the view is rendered three
ways: the whole scene (its alpha, its depth, and the Gaussian of largest blend weight,
`return_ids`), and the fitted object alone (the Gaussians the truth's own masks label as that
object when the trajectory's ground truth is known, else the run's). Then, for a missed pixel
(ground truth object k, predicted something else):

- `fit_empty`: nothing opaque is rendered there (alpha < 0.5);
- `fit_missing`: the fitted object renders nothing there: its surface is not where the object
  is (it is smaller than the object's silhouette, or elsewhere);
- `fit_occluded`: something nearer than the fitted object covers it (a floater or background
  surfel in front: the scene's depth there is more than 5% nearer than the object's);
- `vote_unseen`: the Gaussian shown got no vote (no voting view saw it within eps and delta);
- `vote_few`: fewer votes than `min_votes`;
- `vote_ambiguous`: its top two labels were within `margin` of each other (or tied);
- `segmenter`: it is labelled another label, but the truth's masks, voting on the same views by
  the same rule, label it k: the 2D masks outvoted the truth;
- `vote_outvoted`: it is labelled another label, and so would the truth's masks (or they are
  unknown): it lies on the object but the views it votes in see it outside the object's mask
  (at its edge, or where the fit's surface and the masks disagree);
- `label_render`: the Gaussian shown is labelled k, yet the pixel's label blend (other labelled
  Gaussians behind or beside it, or less than `min_weight` in all) gave another label.

extra (ground truth background, predicted an object): `extra_fit` where the fitted object
renders there (its surface reaches beyond the object's silhouette), `extra_segmenter` where
the Gaussian shown is that object by the run's vote but not by the truth's, `extra_other`.

Whatever the labels, the shift that best aligns the fitted objects' silhouette with the truth's
object pixels (`score.alignment`: `shift_dx`, `shift_dy`, `silhouette_iou`, `shifted_iou`) says
whether the view's object is rendered displaced, as an error in its camera's pose does.
`hidden_px` counts the object's pixels (its ground truth) where the fit covers the fitted
object with a nearer surface (the rule of `fit_occluded`): what a segmenter looking at the
render cannot see. A fit that draws surfaces in front of the object between its photographs
shows here before any label is wrong.

Counts are pixels at the render's resolution (the ground truth resized to it by nearest
neighbour). The groups: fit (fit_*), vote (vote_*, label_render), segmenter.

Per Gaussian (`OutsideTally`): the labelled Gaussians that render outside the object's
silhouette, i.e. the Gaussian shown at an extra pixel that carries the predicted label. For
each: how many extra pixels it shows, in how many views, how many in views that did not vote;
where the surface shown there sits against the object's body in that view (`in_front`: nearer
than the body's nearest 2% of depths by more than 5%, `behind`: farther than its farthest 2%,
`beside`: at the body's depths, outside its silhouette); how it voted (its votes for the label,
for background, in all); and how far it lies from the object's body (`Body`: the largest
cluster of the object's Gaussians; 0 for a Gaussian of it), in body radii.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from sagonline.render.rasterize import RenderOutput
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.io.images import resize_nearest
from sagonline.score.alignment import best_shift
from sagonline.vote.body import Body, extents
from sagonline.vote.consensus import VoteConfig, VoteResult

MISSED = (
    "fit_empty",
    "fit_missing",
    "fit_occluded",
    "vote_unseen",
    "vote_few",
    "vote_ambiguous",
    "segmenter",
    "vote_outvoted",
    "label_render",
)
EXTRA = ("extra_fit", "extra_segmenter", "extra_other")
CAUSE_GROUPS = {
    "fit": ("fit_empty", "fit_missing", "fit_occluded"),
    "vote": ("vote_unseen", "vote_few", "vote_ambiguous", "vote_outvoted", "label_render"),
    "segmenter": ("segmenter",),
}
# Colours of the causes in the recording's diagnosis image (RGB).
CAUSE_COLOURS = {
    "fit_empty": (255, 40, 40),
    "fit_missing": (255, 120, 60),
    "fit_occluded": (255, 180, 0),
    "vote_unseen": (40, 120, 255),
    "vote_few": (0, 200, 255),
    "vote_ambiguous": (255, 240, 60),
    "segmenter": (170, 60, 255),
    "vote_outvoted": (60, 90, 200),
    "label_render": (120, 255, 120),
    "extra_fit": (120, 0, 0),
    "extra_segmenter": (80, 0, 120),
    "extra_other": (0, 90, 0),
}
OCCLUSION = 0.05  # a surface this much nearer than the object's covers it


@dataclass
class GaussianCauses:
    """Per Gaussian (N,): its state in the run's vote and, where known, in the truth's vote."""

    labels: torch.Tensor  # [N] int64, the run's label, -1 unlabelled
    labelled: torch.Tensor  # [N] bool, labels >= 0 (kept beside them: read per view)
    votes: torch.Tensor  # [N] float, votes cast for it
    ambiguous: torch.Tensor  # [N] bool, voted enough but within the margin (or tied)
    truth: torch.Tensor | None  # [N] long label by the truth's masks (-1 unlabelled), or None
    histogram: torch.Tensor | None = None  # [N, K] the run's votes per label
    bodies: dict[int, Body] = field(default_factory=dict, repr=False)

    def body(self, k: int, gaussians: Gaussians) -> Body:
        """Object k's body (`Body`), found once."""
        if k not in self.bodies:
            means = gaussians.means.detach().cpu().numpy()
            self.bodies[k] = Body.of(means, extents(gaussians), self.members(k).numpy())
        return self.bodies[k]

    def drawn(self, k: int, gaussians: Gaussians, body: bool) -> torch.Tensor:  # [1 | 2, N] bool
        """What the diagnosis draws of object k alone: its members, then (with `body`) its body
        where that differs from them."""
        members = self.members(k)
        if not body:
            return members[None]
        kept = torch.from_numpy(self.body(k, gaussians).members)
        return members[None] if torch.equal(kept, members) else torch.stack([members, kept])

    def members(self, k: int) -> torch.Tensor:  # [N] bool
        """The fitted object k: its Gaussians by the truth's vote where known, else the run's."""
        if self.truth is not None:
            return self.truth == k
        return self.labelled & (self.labels == k)

    @classmethod
    def of(cls, run: VoteResult, cfg: VoteConfig, truth: VoteResult | None) -> GaussianCauses:
        votes = run.histogram.sum(1).cpu()
        enough = votes >= cfg.min_votes
        labels = run.labels.cpu()
        labelled = labels >= 0
        truth_labels = truth.labels.cpu() if truth is not None else None
        histogram = run.histogram.cpu()
        return cls(labels, labelled, votes, enough & ~labelled, truth_labels, histogram)


def object_depths(
    gaussians: Gaussians,
    camera: Camera,
    groups: torch.Tensor,  # [G, N] bool, the Gaussians of each fitted object (or its body)
    backend: str,
) -> list[tuple[np.ndarray, np.ndarray]]:  # G x ([H, W] alpha, [H, W] depth)
    """Each fitted object alone in one view, in one walk where the backend can: per group its
    (H, W) alpha and expected depth (NaN where it renders nothing)."""
    from sagonline.render.api import render_coverage

    alphas, depths = (
        t.detach().cpu().numpy()
        for t in render_coverage(gaussians, camera, groups, backend=backend)
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        surface = np.where(alphas > 1e-6, depths / np.maximum(alphas, 1e-6), np.nan)
    return list(zip(alphas, surface, strict=True))


def scene_surface(
    gaussians: Gaussians, camera: Camera, backend: str, whole: RenderOutput | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # [H, W] alpha, depth, int64 ids
    """The whole scene in one view: (H, W) alpha, expected depth (alpha-weighted depth over
    alpha) and the most visible Gaussian (-1: none), from `whole` where the caller rendered it
    with ids, else drawn here: unshaded by the compiled kernel (the walk `object_depths` draws
    the objects with), by `render` with ids elsewhere."""
    from sagonline.render.api import render
    from sagonline.render.backends import resolve_backend

    if whole is not None:
        alpha, depth, ids = whole.alpha, whole.depth, whole.ids
    elif resolve_backend(backend, gaussians.device) == "native":
        from sagonline.render.native import surface_native

        alpha, depth, ids = surface_native(gaussians, camera)
    else:
        out = render(gaussians, camera, backend=backend, return_ids=True)
        alpha, depth, ids = out.alpha, out.depth, out.ids
    if ids is None or alpha.shape != (camera.height, camera.width):
        raise ValueError(f"the view's render must carry ids at {camera.width}x{camera.height}")
    cover = alpha.detach().cpu().numpy()
    expected = depth.detach().cpu().numpy() / np.maximum(cover, 1e-6)
    return cover, expected, ids.cpu().numpy().astype(np.int64)


def diagnose_view(
    gaussians: Gaussians,
    camera: Camera,
    gt: np.ndarray,
    pred: np.ndarray,
    causes: GaussianCauses,
    *,
    ignore: int | None = None,
    backend: str = "auto",
    outside: OutsideTally | None = None,
    voted: bool = False,
    whole: RenderOutput | None = None,
) -> tuple[dict[str, int | float], np.ndarray]:
    """Counts of one view's wrong pixels by cause, its `best_shift`, and an (H, W) uint8 map of
    the causes (index into MISSED + EXTRA, +1; 0: right). gt: the view's ground truth (any size
    of the camera's aspect); pred: the label render at the camera's size. `outside`: adds this
    view's extra pixels to it, per labelled Gaussian shown there (`voted`: the view voted).
    `whole`: the scene's render at the camera with its ids, when the caller has it (rendered
    here otherwise)."""
    h, w = camera.height, camera.width
    truth = resize_nearest(np.asarray(gt), (h, w)).astype(np.int64)
    pred = resize_nearest(np.asarray(pred), (h, w)).astype(np.int64)
    alpha, depth, ids = scene_surface(gaussians, camera, backend, whole)
    valid = np.ones_like(truth, bool) if ignore is None else truth != ignore
    missed = valid & (truth > 0) & (pred != truth)
    extra = valid & (truth == 0) & (pred > 0)
    g = np.clip(ids, 0, None)
    shown = ids >= 0
    run_label = causes.labels.numpy()[g]
    labelled = causes.labelled.numpy()[g] & shown
    votes = causes.votes.numpy()[g]
    ambiguous = causes.ambiguous.numpy()[g]
    truth_label = causes.truth.numpy()[g] if causes.truth is not None else None
    kinds = np.zeros((h, w), np.uint8)

    def mark(name: str, where: np.ndarray) -> None:
        kinds[where & (kinds == 0)] = (MISSED + EXTRA).index(name) + 1

    mark("fit_empty", missed & ((alpha < 0.5) | ~shown))
    hidden = np.zeros((h, w), bool)  # the object's pixels where a nearer surface covers it
    silhouette = np.zeros((h, w), bool)  # where the fitted objects of the truth render
    in_truth = np.unique(truth[valid & (truth > 0)]).tolist()
    for k in sorted(set(in_truth + np.unique(pred[extra]).tolist())):
        if k <= 0:
            continue
        culprit = extra & (pred == k) & labelled & (run_label == k)
        groups = causes.drawn(k, gaussians, body=outside is not None and bool(culprit.any()))
        drawn = object_depths(gaussians, camera, groups, backend)
        obj_alpha, obj_depth = drawn[0]
        with np.errstate(invalid="ignore"):
            covered = depth < (1 - OCCLUSION) * obj_depth  # False where the object renders nothing
        hidden |= valid & (truth == k) & covered
        silhouette |= (obj_alpha >= 0.5) & (k in in_truth)
        at_k = missed & (truth == k)
        mark("fit_missing", at_k & (obj_alpha < 0.5))
        mark("fit_occluded", at_k & covered)
        mark("extra_fit", extra & (pred == k) & (obj_alpha >= 0.5))
        if outside is not None and culprit.any():
            body_alpha, body_depth = drawn[-1]  # the object itself where it is its body
            outside.add(ids[culprit], depth[culprit], body_alpha, body_depth, voted)
    mark("label_render", missed & labelled & (run_label == truth))
    unlabelled = missed & ~labelled
    mark("vote_unseen", unlabelled & (votes == 0))
    mark("vote_few", unlabelled & (votes > 0) & ~ambiguous)
    mark("vote_ambiguous", unlabelled)
    if truth_label is not None:
        mark("segmenter", missed & labelled & (truth_label == truth))
        mark("extra_segmenter", extra & labelled & (run_label == pred) & (truth_label != pred))
    mark("vote_outvoted", missed)
    mark("extra_other", extra)
    counts = {name: int((kinds == i + 1).sum()) for i, name in enumerate(MISSED + EXTRA)}
    counts["missed_px"] = int(missed.sum())
    counts["extra_px"] = int(extra.sum())
    counts["object_px"] = int((valid & (truth > 0)).sum())
    counts["hidden_px"] = int(hidden.sum())
    return {**counts, **best_shift(valid & (truth > 0), silhouette)}, kinds


POSITIONS = ("in_front", "beside", "behind")


@dataclass
class OutsideTally:
    """Over the scored views: per labelled Gaussian shown at an extra pixel, its extra pixels
    by position (POSITIONS), those in views that did not vote, and the views it showed in."""

    pixels: dict[int, np.ndarray] = field(default_factory=dict)  # id -> [3 positions, held-out]
    views: dict[int, int] = field(default_factory=dict)

    def add(
        self,
        ids: np.ndarray,  # [P] the Gaussian shown at each extra pixel
        depth: np.ndarray,  # [P] the scene's depth there
        obj_alpha: np.ndarray,  # [H, W] the object's body alone
        obj_depth: np.ndarray,  # [H, W] its depth (NaN where it renders nothing)
        voted: bool,
    ) -> None:
        if ids.size == 0:
            return
        inside = obj_depth[(obj_alpha >= 0.5) & np.isfinite(obj_depth)]
        position = np.ones(ids.shape, np.int64)  # beside, unless the object's depths say more
        if inside.size:
            near, far = np.percentile(inside, [2, 98])
            position[depth < (1 - OCCLUSION) * near] = 0
            position[depth > (1 + OCCLUSION) * far] = 2
        shown, which = np.unique(ids, return_inverse=True)
        by_position = np.zeros((len(shown), 3), np.int64)
        np.add.at(by_position, (which.reshape(-1), position), 1)
        for g, counts in zip(shown.tolist(), by_position, strict=True):
            row = self.pixels.setdefault(g, np.zeros(4, np.int64))
            row[:3] += counts
            row[3] += 0 if voted else int(counts.sum())
            self.views[g] = self.views.get(g, 0) + 1

    def rows(self, gaussians: Gaussians, causes: GaussianCauses) -> list[dict]:
        """One row per Gaussian, most extra pixels first: id, label, position (x, y, z), extra
        pixels (all, by position, in views that did not vote), views, its votes (for its label,
        for background, all) and its distance from the object's body in object radii (0: part
        of it; `Body`)."""
        if not self.pixels:
            return []
        ids = np.array(sorted(self.pixels, key=lambda g: -int(self.pixels[g][:3].sum())))
        means = gaussians.means.detach().cpu().numpy()
        labels = causes.labels.numpy()
        hist = causes.histogram.numpy() if causes.histogram is not None else None
        distance = np.full(len(ids), np.nan)
        for k in np.unique(labels[ids]).tolist():
            of_k = labels[ids] == k
            distance[of_k] = causes.body(k, gaussians).distance(means, ids[of_k])
        rows = []
        for g, d in zip(ids.tolist(), distance.tolist(), strict=True):
            px, k = self.pixels[g], int(labels[g])
            row = {"gaussian": g, "label": k, "x": means[g, 0], "y": means[g, 1], "z": means[g, 2]}
            row |= {
                "extra_px": int(px[:3].sum()),
                **dict(zip(POSITIONS, px[:3].tolist(), strict=True)),
            }
            row |= {"extra_px_not_voting": int(px[3]), "views": self.views[g]}
            if hist is not None:
                votes = hist[g]
                row |= {"votes_label": float(votes[k]), "votes_background": float(votes[0])}
                row |= {"votes": float(votes.sum())}
            row["body_distance_radii"] = None if np.isnan(d) else round(d, 4)
            rows.append(row)
        return rows


def outside_summary(rows: list[dict], extra_px: int) -> dict:
    """The extra pixels that labelled Gaussians show, summed over `OutsideTally.rows`: how
    many Gaussians, their share of all the views' `extra_px`, the share by position, in views
    that did not vote, shown by floating Gaussians (apart from the object's `Body`), and by
    Gaussians whose own votes were at least 90% for their label."""
    total = sum(r["extra_px"] for r in rows)
    out: dict = {"gaussians": len(rows), "extra_px": total}
    out["share_of_extra"] = total / extra_px if extra_px else None
    if not total:
        return out

    def share(pick) -> float:
        return sum(r["extra_px"] for r in rows if pick(r)) / total

    for name in POSITIONS:
        out[f"share_{name}"] = sum(r[name] for r in rows) / total
    out["share_not_voting"] = sum(r["extra_px_not_voting"] for r in rows) / total
    out["share_floating"] = share(lambda r: (r["body_distance_radii"] or 0) > 0)
    if "votes" in rows[0]:
        out["share_confident"] = share(lambda r: r["votes_label"] >= 0.9 * max(r["votes"], 1))
    return out


def shares(rows: list[dict]) -> dict[str, float | None]:
    """Over several views' counts: each cause group's share of the missed pixels (fit, vote,
    segmenter) and each cause's (None where nothing was missed); `hidden`: the share of the
    objects' pixels that the fit covers with a nearer surface, whatever the labels (None
    without object pixels), and `hidden_views`: the views where it covers more than a tenth."""
    missed = sum(r.get("missed_px", 0) for r in rows)
    objects = sum(r.get("object_px", 0) for r in rows)
    out: dict[str, float | None] = {"missed_px": missed}
    out["hidden"] = sum(r.get("hidden_px", 0) for r in rows) / objects if objects else None
    out["hidden_views"] = sum(
        1 for r in rows if r.get("object_px") and r.get("hidden_px", 0) > 0.1 * r["object_px"]
    )
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


__all__ = [
    "CAUSE_GROUPS",
    "EXTRA",
    "MISSED",
    "POSITIONS",
    "GaussianCauses",
    "OutsideTally",
    "diagnose_view",
    "outside_summary",
    "shares",
]
