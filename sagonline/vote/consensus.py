"""Lift 2D label masks to one discrete label per Gaussian.

`rgc` is the paper's Rasterization-aware Geometric Consensus: for every pixel of every selected
mask, walk its Gaussians front to back; a Gaussian votes for the pixel's label only while the
transmittance before it is T_i > eps (the walk stops once T falls to eps) and only if its
projected centre lies within delta px of the pixel centre (each such pair +1, or its blend weight
alpha_i T_i with `weighting=blend`, not the paper's). One vote histogram per Gaussian;
the label is the argmax; too few votes (< min_votes) or an ambiguous winner (top-1 share minus
top-2 share < margin, or a tie) leaves the Gaussian unlabelled.

Two baselines share the interface:
- `flashsplat`: every traced contribution adds its blend weight alpha_i T_i to its label;
  normalised per Gaussian, a background slack is added to label 0, argmax.
- `weighted_mean` (GaussianCut / LUDVIG): the alpha_i T_i-weighted mean of each label's
  indicator; a Gaussian takes the best non-background label if its mean reaches `threshold`
  (0.9), else background.

Labels: (N,) int64, -1 unlabelled, 0 background, 1.. the objects, from the vote to every
output (`VoteResult.labels`).

Each method is a vote rule registered in `plugins.VOTE_RULES` under its name: the pairs its
kernels count (`VoteConfig.rule`, a `render.rule.VoteRule`) and how a histogram becomes labels
(its `decide`). A setting a method does not read is refused when the config is built
(`consensus=flashsplat consensus.delta=1.5` stops, naming delta).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from sagonline.core.plugins import VOTE_RULES
from sagonline.core.settings import check_settings
from sagonline.core.store import stored
from sagonline.render.rasterize import T_STOP
from sagonline.render.rule import WEIGHTINGS, VoteRule
from sagonline.render.vote import vote_into
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.vote.body import extents, keep_bodies
from sagonline.vote.fill import fill_from_neighbours
from sagonline.vote.masks import MaskError, check_mask


@dataclass
class VoteConfig:
    """Settings of the vote. `num_masks`/`stride`/`selection` choose which frames vote."""

    method: str = "rgc"
    """A registered vote rule: rgc (the paper's), flashsplat or weighted_mean
    (`python -m sagonline plugins vote-rules`)."""
    eps: float = VoteRule.eps
    """rgc: a Gaussian votes only while T_i > eps; a pixel's walk stops when T falls to eps
    (the default, the paper's 0.01, is `render.rule.VoteRule`'s)."""
    delta: float | None = VoteRule.delta
    """rgc: ... and only if its projected centre lies within delta px of the pixel centre;
    null: no distance rule (default: the paper's 2 px, `VoteRule`'s)."""
    weighting: str = VoteRule.weighting
    """rgc: what one (pixel, Gaussian) pair adds to its label: count (+1, the paper's) or blend
    (its blend weight alpha_i T_i, as FlashSplat weighs; then `min_votes` is a total weight:
    one fully visible pixel is one vote)."""
    min_votes: int = 1
    """Fewer votes leave a Gaussian unlabelled (at least 1: a Gaussian no view saw is never
    labelled)."""
    margin: float = 0.2
    """A top-1 minus top-2 vote share below this (or a tie) leaves it unlabelled."""
    num_masks: int | None = None
    """How many masks vote (None: all of those `stride` picks)."""
    stride: int = 1
    """Every stride-th mask is a candidate to vote."""
    selection: str = "uniform"
    """Which num_masks of the candidates: uniform (evenly spaced), first, or random (seeded)."""
    seed: int = 0
    """Seeds `selection=random`."""
    background_slack: float = 0.0
    """flashsplat: added to the background's normalised weight."""
    threshold: float = 0.9
    """weighted_mean: the weighted mean a foreground label must reach."""
    fill: int = 0
    """Unlabelled Gaussians take the label a strict majority of their `fill` nearest labelled
    neighbours in 3D share (neighbours within 4x the labelled Gaussians' median spacing);
    0: off, the paper's protocol (`fill_from_neighbours`)."""
    body: bool = False
    """Each object's labels kept on its body, the largest cluster of its touching Gaussians
    (centres nearer than the sum of their largest scales); those touching nothing of it are
    left unlabelled. Off: the paper's protocol (`vote.body.keep_bodies`)."""

    def __post_init__(self) -> None:
        n = self.num_masks
        methods = VOTE_RULES.keys()
        check_settings(
            "consensus",
            method=(self.method in methods, self.method, f"one of {methods}"),
            selection=(
                self.selection in ("uniform", "first", "random"),
                self.selection,
                "uniform, first or random",
            ),
            eps=(0 <= self.eps < 1, self.eps, "a transmittance in [0, 1)"),
            delta=(
                self.delta is None or self.delta > 0,
                self.delta,
                "a distance in pixels > 0, or null (no distance rule)",
            ),
            weighting=(self.weighting in WEIGHTINGS, self.weighting, f"one of {WEIGHTINGS}"),
            min_votes=(self.min_votes >= 1, self.min_votes, ">= 1"),
            margin=(0 <= self.margin < 1, self.margin, "a share gap in [0, 1)"),
            num_masks=(n is None or n > 0, n, "> 0, or null for all masks"),
            stride=(self.stride >= 1, self.stride, ">= 1"),
            background_slack=(self.background_slack >= 0, self.background_slack, ">= 0"),
            threshold=(0 <= self.threshold <= 1, self.threshold, "in [0, 1]"),
            fill=(0 <= self.fill <= 64, self.fill, "in [0, 64] neighbours (0: off)"),
        )
        self.method_rule().check_reads(self)

    def method_rule(self) -> VoteMethod:
        """The registered method this config names."""
        return VOTE_RULES.build(self.method, {})

    @property
    def rule(self) -> VoteRule:
        """The rule the kernels apply, built once from these settings by the method."""
        return self.method_rule().rule(self)


# The settings every method reads: which masks vote, and the fill and body rule after it.
SELECTION = ("method", "num_masks", "stride", "selection", "seed", "fill", "body")


@dataclass(frozen=True)
class VoteMethod:
    """A registered vote rule: the VoteConfig settings it reads (besides SELECTION), the kernel
    rule it builds from them, and how an (N, K) histogram becomes labels (N,) and labelled
    (N,)."""

    reads: tuple[str, ...]
    rule: Callable[[VoteConfig], VoteRule]
    decide: Callable[[torch.Tensor, VoteConfig], tuple[torch.Tensor, torch.Tensor]]

    def check_reads(self, cfg: VoteConfig) -> None:
        """Refuse a setting this method does not read that differs from its default: it would
        be ignored without a word."""
        defaults = VoteConfig.__dataclass_fields__
        for f in fields(cfg):
            if f.name in SELECTION or f.name in self.reads:
                continue
            if getattr(cfg, f.name) != defaults[f.name].default:
                raise ValueError(
                    f"consensus.{f.name}={getattr(cfg, f.name)!r}: the method {cfg.method} "
                    f"does not read {f.name} (it reads {', '.join(self.reads) or 'nothing'})"
                )


@stored
@dataclass
class VoteResult:
    """labels: (N,) int64, -1 unlabelled, 0 background, 1.. the objects (the one encoding of
    every output and label render); histogram: (N, K) float32 votes or weights; frames: the
    trajectory indices of the masks that voted, in the order they voted; stats: fractions,
    counts and timings."""

    labels: torch.Tensor
    histogram: torch.Tensor
    frames: list[int]
    stats: dict = field(default_factory=dict)


def select_frames(num_frames: int, cfg: VoteConfig) -> list[int]:
    """Indices of the masks that vote: every `stride`-th, then `num_masks` of those."""
    candidates = list(range(0, num_frames, cfg.stride))
    n = cfg.num_masks
    if n is None or n >= len(candidates):
        return candidates
    if n <= 0:
        raise ValueError(f"num_masks must be positive, got {n}")
    if cfg.selection == "first":
        return candidates[:n]
    if cfg.selection == "random":
        rng = np.random.default_rng(cfg.seed)
        return sorted(rng.choice(candidates, size=n, replace=False).tolist())
    picks = np.linspace(0, len(candidates) - 1, n).round().astype(int)
    return [candidates[i] for i in sorted(set(picks.tolist()))]


class VoteAccumulator:
    """The running (N, K) vote histogram of one method: views are added one by one by the vote
    op (`render.vote.vote_into`), labels are read off at any time (`labels`), the result with
    its statistics at the end (`result`). means: (N, 3) the Gaussians' centres, needed only by
    the fill and the body rule (`consensus.fill`, `consensus.body`); extents: (N,) their largest
    scales, needed by the body rule (`vote.body.extents`)."""

    def __init__(
        self,
        num_gaussians: int,
        num_labels: int,
        cfg: VoteConfig,
        device: torch.device | str = "cpu",
        means: torch.Tensor | None = None,
        extents: np.ndarray | None = None,
    ):
        self.cfg, self.k, self.rule, self.means = cfg, num_labels, cfg.rule, means
        self.extents = extents
        self.hist = torch.zeros(num_gaussians, num_labels, dtype=torch.float64, device=device)
        self.frames: list[int] = []
        self.pairs = 0  # (pixel, Gaussian) pairs that voted
        self.seconds = 0.0  # spent in the vote op and reading labels off
        self.dropped: torch.Tensor | None = None  # [N] bool, off their object's body

    def grow(self, num_labels: int) -> None:
        """Make room for labels up to num_labels - 1 (a segmenter may name more objects than
        the prompt did)."""
        if num_labels > self.k:
            extra = self.hist.new_zeros(self.hist.shape[0], num_labels - self.k)
            self.hist = torch.cat([self.hist, extra], dim=1).contiguous()
            self.k = num_labels

    def add_view(
        self,
        gaussians: Gaussians,
        camera: Camera,
        mask,
        backend: str,
        where: str = "mask",
        frame: int | None = None,
    ) -> int:
        """Vote one view's (H, W) label map (`where` names it in errors; `frame`: its index in
        the trajectory); returns the pairs that voted."""
        start = time.perf_counter()
        labels = check_mask(mask, camera, self.k, where).view(camera.height, camera.width)
        cast = vote_into(
            gaussians, camera, labels.to(gaussians.device), self.rule, self.hist, backend=backend
        )
        self.pairs += cast
        self.frames.append(len(self.frames) if frame is None else frame)
        self.seconds += time.perf_counter() - start
        return cast

    def labels(self) -> torch.Tensor:  # [N] int64, -1 unlabelled
        """The labels of the histogram so far: the method's rule, then the config's fill (the
        body rule, `consensus.body`, applies to the final labels, `result`)."""
        return self._decide(final=False)[0]

    def _decide(self, final: bool = True) -> tuple[torch.Tensor, torch.Tensor]:  # [N], [N] filled
        start = time.perf_counter()
        labels = decide(self.hist, self.cfg)
        filled = torch.zeros_like(labels, dtype=torch.bool)
        if (self.cfg.fill or self.cfg.body) and self.means is None:
            raise ValueError("consensus.fill and consensus.body need the Gaussians' centres")
        if self.cfg.body and self.extents is None:
            raise ValueError("consensus.body needs the Gaussians' extents (extents=)")
        if self.cfg.fill:
            labels, filled = fill_from_neighbours(self.means, labels, self.cfg.fill)
        if self.cfg.body and final:
            labels, self.dropped = keep_bodies(self.means, self.extents, labels)
        self.seconds += time.perf_counter() - start
        return labels, filled

    def result(self) -> VoteResult:
        """The labels, the histogram (float32), the frames that voted and the statistics."""
        labels, filled = self._decide()
        total = self.hist.sum(1)
        voted = total > 0
        labelled = labels >= 0
        off = self.dropped if self.dropped is not None else torch.zeros_like(labelled)
        n = len(self.frames)
        stats = {
            "fraction_filled": float(filled.float().mean()) if len(labels) else 0.0,
            "fraction_off_body": float(off.float().mean()) if len(labels) else 0.0,
            "num_masks": n,
            "fraction_labelled": float(labelled.float().mean()) if len(labels) else 0.0,
            "fraction_voted": float(voted.float().mean()) if len(labels) else 0.0,
            "fraction_ambiguous": float((voted & ~labelled & ~filled & ~off).float().mean())
            if len(labels)
            else 0.0,
            "votes_per_gaussian_mean": float(total[voted].mean()) if voted.any() else 0.0,
            "votes_per_gaussian_median": float(total[voted].median()) if voted.any() else 0.0,
            "votes_cast": self.pairs,
            "aggregation_s": self.seconds,
            "ms_per_mask": 1000.0 * self.seconds / max(n, 1),
        }
        return VoteResult(labels, self.hist.float(), list(self.frames), stats)


def decide(
    hist: torch.Tensor,  # [N, K] votes or blend weights
    cfg: VoteConfig,
) -> torch.Tensor:  # [N] int64, -1 unlabelled
    """Histogram -> labels by the method's rule (see the module docstring): -1 where it leaves
    a Gaussian unlabelled."""
    labels, labelled = cfg.method_rule().decide(hist, cfg)
    return torch.where(labelled, labels.long(), torch.full_like(labels.long(), -1))


def decide_majority(
    hist: torch.Tensor,  # [N, K] votes
    cfg: VoteConfig,
) -> tuple[torch.Tensor, torch.Tensor]:  # [N] labels, [N] labelled
    """rgc: the label of most votes, unless fewer than min_votes, a tie, or a top-1 minus top-2
    share below margin."""
    k = hist.shape[1]
    total = hist.sum(1)
    top2 = hist.topk(min(2, k), dim=1)
    labels = top2.indices[:, 0]
    second = top2.values[:, 1] if k > 1 else torch.zeros_like(total)
    share_gap = (top2.values[:, 0] - second) / total.clamp_min(1e-12)
    labelled = (total >= cfg.min_votes) & (top2.values[:, 0] > second)
    return labels, labelled & (share_gap >= cfg.margin)


def decide_flashsplat(
    hist: torch.Tensor,  # [N, K] blend weights
    cfg: VoteConfig,
) -> tuple[torch.Tensor, torch.Tensor]:  # [N] labels, [N] labelled
    """flashsplat: normalised weights, background slack added to label 0, argmax."""
    total = hist.sum(1)
    norm = hist / total.clamp_min(1e-12)[:, None]
    norm[:, 0] += cfg.background_slack
    return norm.argmax(1), total > 0


def decide_weighted_mean(
    hist: torch.Tensor,  # [N, K] blend weights
    cfg: VoteConfig,
) -> tuple[torch.Tensor, torch.Tensor]:  # [N] labels, [N] labelled
    """weighted_mean: the best foreground label whose weighted mean reaches threshold, else
    background."""
    total = hist.sum(1)
    mean = hist / total.clamp_min(1e-12)[:, None]
    best_val, best = mean[:, 1:].max(1)
    labels = torch.where(best_val >= cfg.threshold, best + 1, torch.zeros_like(best))
    return labels, total > 0


def count_rule(cfg: VoteConfig) -> VoteRule:
    """rgc's pairs: T_i > eps and the centre within delta px, +1 each (weighting count, the
    paper's) or alpha_i T_i each (blend)."""
    return VoteRule(cfg.eps, cfg.delta, cfg.weighting)


def blend_rule(cfg: VoteConfig) -> VoteRule:
    """The weighted methods' pairs: every composited one (T_i > T_STOP), alpha_i T_i each."""
    return VoteRule(T_STOP, None, "blend")


@dataclass
class NoSettings:
    """A vote rule's settings live on VoteConfig (`consensus.*`): it names those it reads."""


for _key, _method, _summary in (
    (
        "rgc",
        VoteMethod(
            ("eps", "delta", "weighting", "min_votes", "margin"), count_rule, decide_majority
        ),
        "the paper's consensus: visible (T > eps), aligned (delta px) votes, majority, margin",
    ),
    (
        "flashsplat",
        VoteMethod(("background_slack",), blend_rule, decide_flashsplat),
        "FlashSplat: alpha*T weights per label, normalised, background slack, argmax",
    ),
    (
        "weighted_mean",
        VoteMethod(("threshold",), blend_rule, decide_weighted_mean),
        "GaussianCut / LUDVIG: the alpha*T-weighted mean of each label, threshold",
    ),
):
    VOTE_RULES.register(_key, NoSettings, lambda cfg, m=_method: m, summary=_summary)


def consensus_vote(
    gaussians: Gaussians,
    cameras: Sequence[Camera],
    masks: Sequence,
    num_labels: int,
    cfg: VoteConfig | None = None,
    *,
    backend: str = "auto",
) -> VoteResult:
    """Vote every selected (camera, mask) pair into one label per Gaussian, in one call (the
    pipeline streams the same accumulator view by view: `pipeline.stage_one.StageOne`).

    cameras: T views; masks: T label maps (H, W) with ids in [0, num_labels), one per view.
    """
    cfg = cfg or VoteConfig()
    if len(cameras) != len(masks):
        raise MaskError(f"{len(cameras)} cameras but {len(masks)} masks")
    acc = VoteAccumulator(
        len(gaussians), num_labels, cfg, gaussians.device, gaussians.means, extents(gaussians)
    )
    for f in select_frames(len(cameras), cfg):
        acc.add_view(gaussians, cameras[f], masks[f], backend, f"mask of frame {f}", frame=f)
    return acc.result()
