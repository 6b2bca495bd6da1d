"""The vote methods, each a plug-in of `plugins.VOTE_RULES` with its own typed settings.

A method is its settings dataclass (`vote.settings`: the `consensus.*` settings it reads, each
with its default, its rule and its documentation), the kernel rule it builds from them
(`render.rule.VoteRule`: which (pixel, Gaussian) pairs vote, for how much) and how an (N, K)
histogram becomes labels. `vote.settings.VoteConfig` holds every method's settings under flat
names for Hydra and the files runs write; the command line's vote flags (`sagonline segment
--eps ...`) and the viewer's vote panel are generated from the dataclasses
(`vote.settings.vote_setting_specs`), without importing this module.

- `rgc`: the paper's consensus. Visible (T_i > eps), aligned (centre within delta px) pairs,
  +1 each (or alpha_i T_i with `weighting=blend`, not the paper's); the label of most votes,
  unless fewer than `min_votes`, a tie, or a top-1 minus top-2 share below `margin`.
- `flashsplat`: every composited pair adds alpha_i T_i to its label; normalised per Gaussian,
  `background_slack` added to label 0, argmax.
- `weighted_mean` (GaussianCut / LUDVIG): the alpha_i T_i-weighted mean of each label's
  indicator; the best foreground label whose mean reaches `threshold`, else background.
"""

from __future__ import annotations

import typing
from collections.abc import Callable
from dataclasses import dataclass

import torch

from sagonline.core.plugins import VOTE_RULES
from sagonline.render.rasterize import T_STOP
from sagonline.render.rule import VoteRule
from sagonline.vote.settings import (
    BUILTIN_METHODS,
    FlashSplatSettings,
    RgcSettings,
    WeightedMeanSettings,
)

# (labels, labelled): (N,) int64 and (N,) bool, from an (N, K) histogram and a method's settings
Decision = tuple[torch.Tensor, torch.Tensor]


@dataclass(frozen=True)
class VoteMethod:
    """A registered method as the vote runs it: the kernel rule built from its settings, and
    how an (N, K) histogram becomes labels (N,) and labelled (N,)."""

    rule: Callable[[typing.Any], VoteRule]
    decide: Callable[[torch.Tensor, typing.Any], Decision]


def count_rule(s) -> VoteRule:
    """rgc's pairs: T_i > eps and the centre within delta px, +1 each (weighting count, the
    paper's) or alpha_i T_i each (blend)."""
    return VoteRule(s.eps, s.delta, getattr(s, "weighting", VoteRule.weighting))


def blend_rule(s) -> VoteRule:
    """The weighted methods' pairs: every composited one (T_i > T_STOP), alpha_i T_i each."""
    return VoteRule(T_STOP, None, "blend")


def decide_majority(
    hist: torch.Tensor,  # [N, K] votes
    s: RgcSettings,
) -> Decision:
    """rgc: the label of most votes, unless fewer than min_votes, a tie, or a top-1 minus top-2
    share below margin."""
    k = hist.shape[1]
    total = hist.sum(1)
    top2 = hist.topk(min(2, k), dim=1)
    labels = top2.indices[:, 0]
    second = top2.values[:, 1] if k > 1 else torch.zeros_like(total)
    share_gap = (top2.values[:, 0] - second) / total.clamp_min(1e-12)
    labelled = (total >= s.min_votes) & (top2.values[:, 0] > second)
    return labels, labelled & (share_gap >= s.margin)


def decide_flashsplat(
    hist: torch.Tensor,  # [N, K] blend weights
    s: FlashSplatSettings,
) -> Decision:
    """flashsplat: normalised weights, background slack added to label 0, argmax."""
    total = hist.sum(1)
    norm = hist / total.clamp_min(1e-12)[:, None]
    norm[:, 0] += s.background_slack
    return norm.argmax(1), total > 0


def decide_weighted_mean(
    hist: torch.Tensor,  # [N, K] blend weights
    s: WeightedMeanSettings,
) -> Decision:
    """weighted_mean: the best foreground label whose weighted mean reaches threshold, else
    background."""
    total = hist.sum(1)
    mean = hist / total.clamp_min(1e-12)[:, None]
    best_val, best = mean[:, 1:].max(1)
    labels = torch.where(best_val >= s.threshold, best + 1, torch.zeros_like(best))
    return labels, total > 0


for _key, _method, _summary in (
    (
        "rgc",
        VoteMethod(count_rule, decide_majority),
        "the paper's consensus: visible (T > eps), aligned (delta px) votes, majority, margin",
    ),
    (
        "flashsplat",
        VoteMethod(blend_rule, decide_flashsplat),
        "FlashSplat: alpha*T weights per label, normalised, background slack, argmax",
    ),
    (
        "weighted_mean",
        VoteMethod(blend_rule, decide_weighted_mean),
        "GaussianCut / LUDVIG: the alpha*T-weighted mean of each label, threshold",
    ),
):
    VOTE_RULES.register(_key, BUILTIN_METHODS[_key], lambda s, m=_method: m, summary=_summary)
