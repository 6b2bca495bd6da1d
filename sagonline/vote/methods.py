"""The vote methods, each a plug-in of `plugins.VOTE_RULES` with its own typed settings.

A method is its settings dataclass (the `consensus.*` settings it reads, each with its default,
its rule and its documentation), the kernel rule it builds from them (`render.rule.VoteRule`:
which (pixel, Gaussian) pairs vote, for how much) and how an (N, K) histogram becomes labels.
`vote.consensus.VoteConfig` holds every method's settings under flat names for Hydra and the
files runs write; the command line's vote flags (`sagonline segment --eps ...`) and the
viewer's vote panel are generated from these dataclasses (`setting_specs`).

- `rgc`: the paper's consensus. Visible (T_i > eps), aligned (centre within delta px) pairs,
  +1 each (or alpha_i T_i with `weighting=blend`, not the paper's); the label of most votes,
  unless fewer than `min_votes`, a tie, or a top-1 minus top-2 share below `margin`.
- `flashsplat`: every composited pair adds alpha_i T_i to its label; normalised per Gaussian,
  `background_slack` added to label 0, argmax.
- `weighted_mean` (GaussianCut / LUDVIG): the alpha_i T_i-weighted mean of each label's
  indicator; the best foreground label whose mean reaches `threshold`, else background.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap
import types
import typing
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields

import torch

from sagonline.core.plugins import VOTE_RULES
from sagonline.core.settings import check_settings
from sagonline.render.rasterize import T_STOP
from sagonline.render.rule import WEIGHTINGS, VoteRule

# (labels, labelled): (N,) int64 and (N,) bool, from an (N, K) histogram and a method's settings
Decision = tuple[torch.Tensor, torch.Tensor]


def setting(default, low=None, high=None, step=None, choices=None):
    """A method setting's field: its default, and the bounds, step or choices the command line
    and the viewer's panel offer for it (the setting's own rule is its `__post_init__`'s)."""
    meta = {"low": low, "high": high, "step": step, "choices": choices}
    return field(default=default, metadata={k: v for k, v in meta.items() if v is not None})


@dataclass
class RgcSettings:
    """rgc, the paper's Rasterization-aware Geometric Consensus."""

    eps: float = setting(VoteRule.eps, low=0.0, high=0.999, step=0.001)
    """A Gaussian votes only while T_i > eps; a pixel's walk stops when T falls to eps (the
    paper's 0.01, `render.rule.VoteRule`'s)."""
    delta: float | None = setting(VoteRule.delta, low=0.1, step=0.5)
    """... and only if its projected centre lies within delta px of the pixel centre; null: no
    distance rule (the paper's 2 px, `VoteRule`'s)."""
    weighting: str = setting(VoteRule.weighting, choices=WEIGHTINGS)
    """What one (pixel, Gaussian) pair adds to its label: count (+1, the paper's) or blend (its
    blend weight alpha_i T_i, as FlashSplat weighs; then `min_votes` is a total weight: one
    fully visible pixel is one vote)."""
    min_votes: int = setting(1, low=1, step=1)
    """Fewer votes leave a Gaussian unlabelled (at least 1: a Gaussian no view saw is never
    labelled)."""
    margin: float = setting(0.2, low=0.0, high=0.99, step=0.05)
    """A top-1 minus top-2 vote share below this (or a tie) leaves it unlabelled."""

    def __post_init__(self) -> None:
        check_settings(
            "consensus",
            eps=(0 <= self.eps < 1, self.eps, "a transmittance in [0, 1)"),
            delta=(
                self.delta is None or self.delta > 0,
                self.delta,
                "a distance in pixels > 0, or null (no distance rule)",
            ),
            weighting=(self.weighting in WEIGHTINGS, self.weighting, f"one of {WEIGHTINGS}"),
            min_votes=(self.min_votes >= 1, self.min_votes, ">= 1"),
            margin=(0 <= self.margin < 1, self.margin, "a share gap in [0, 1)"),
        )


@dataclass
class FlashSplatSettings:
    """flashsplat: alpha T weights per label, normalised, a background slack, argmax."""

    background_slack: float = setting(0.0, low=0.0, step=0.05)
    """Added to the background's normalised weight."""

    def __post_init__(self) -> None:
        slack = self.background_slack
        check_settings("consensus", background_slack=(slack >= 0, slack, ">= 0"))


@dataclass
class WeightedMeanSettings:
    """weighted_mean: the alpha T-weighted mean of each label, a threshold."""

    threshold: float = setting(0.9, low=0.0, high=1.0, step=0.05)
    """The weighted mean a foreground label must reach."""

    def __post_init__(self) -> None:
        t = self.threshold
        check_settings("consensus", threshold=(0 <= t <= 1, t, "in [0, 1]"))


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


for _key, _settings, _method, _summary in (
    (
        "rgc",
        RgcSettings,
        VoteMethod(count_rule, decide_majority),
        "the paper's consensus: visible (T > eps), aligned (delta px) votes, majority, margin",
    ),
    (
        "flashsplat",
        FlashSplatSettings,
        VoteMethod(blend_rule, decide_flashsplat),
        "FlashSplat: alpha*T weights per label, normalised, background slack, argmax",
    ),
    (
        "weighted_mean",
        WeightedMeanSettings,
        VoteMethod(blend_rule, decide_weighted_mean),
        "GaussianCut / LUDVIG: the alpha*T-weighted mean of each label, threshold",
    ),
):
    VOTE_RULES.register(_key, _settings, lambda s, m=_method: m, summary=_summary)


# --- what the command line and the panel are generated from ---------------------------------


@dataclass(frozen=True)
class SettingSpec:
    """One method setting as a control: its name, type (float, int, str, bool), whether null
    is allowed (off), its default, bounds, step, choices, and its documentation."""

    name: str
    kind: type
    optional: bool
    default: typing.Any
    doc: str
    low: float | None = None
    high: float | None = None
    step: float | None = None
    choices: tuple[str, ...] | None = None
    readers: tuple[str, ...] = ()
    """The methods that read it (filled by `vote.consensus.vote_setting_specs`)."""


def setting_specs(settings_class: type) -> list[SettingSpec]:
    """The controls of a settings dataclass, in field order."""
    hints = typing.get_type_hints(settings_class)
    docs = field_docs(settings_class)
    specs = []
    for f in fields(settings_class):
        kind, optional = hints[f.name], False
        if isinstance(kind, types.UnionType):
            args = [a for a in typing.get_args(kind) if a is not type(None)]
            kind, optional = args[0], True
        default = f.default if f.default is not MISSING else f.default_factory()
        meta = dict(f.metadata)
        specs.append(SettingSpec(f.name, kind, optional, default, docs.get(f.name, ""), **meta))
    return specs


def method_specs() -> dict[str, list[SettingSpec]]:
    """Every registered method's settings as controls: method key -> its specs."""
    return {plugin.key: setting_specs(plugin.config) for plugin in VOTE_RULES}


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """A dataclass's field docstrings (the string under each field), as one line each."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):  # no source (built in a REPL)
        return {}
    cls_node = tree.body[0]
    if not isinstance(cls_node, ast.ClassDef):
        return {}
    body, docs = cls_node.body, {}
    for node, after in zip(body, body[1:], strict=False):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
            docs[node.target.id] = " ".join(str(after.value.value).split())
    return docs
