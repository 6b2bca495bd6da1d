"""The vote's settings, apart from the vote (no PyTorch): each built-in method's typed settings
(`RgcSettings`, `FlashSplatSettings`, `WeightedMeanSettings`: each setting's default, rule and
documentation), `VoteConfig`, which holds every method's settings under one flat name each
(`consensus.*` for Hydra and the files runs write), and the controls generated from them (the
command line's vote flags, the viewer's vote panel: `vote_setting_specs`).

The rules and decisions the methods build from these are `vote.methods`'; the vote itself is
`vote.consensus`'. A command that only offers the settings (`sagonline segment --help`) reads
this module alone.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap
import types
import typing
from dataclasses import MISSING, dataclass, field, fields, replace

from sagonline.core.plugins import VOTE_RULES
from sagonline.core.settings import check_settings
from sagonline.render.rule import WEIGHTINGS, VoteRule


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


BUILTIN_METHODS: dict[str, type] = {
    "rgc": RgcSettings,
    "flashsplat": FlashSplatSettings,
    "weighted_mean": WeightedMeanSettings,
}
"""The built-in methods' settings by key (`vote.methods` registers each with its rule)."""


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
    """The methods that read it (filled by `vote_setting_specs`)."""


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
    """Every registered method's settings as controls: method key -> its specs, by key. The
    built-ins' come from `BUILTIN_METHODS` while no other module can register a method, so the
    controls cost no import of the vote (PyTorch)."""
    if VOTE_RULES.declared_only():
        configs = dict(BUILTIN_METHODS)
    else:
        configs = {plugin.key: plugin.config for plugin in VOTE_RULES}
    return {key: setting_specs(configs[key]) for key in sorted(configs)}


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


# --- every method's settings under one flat name each ----------------------------------------


@dataclass
class VoteConfig:
    """Settings of the vote: its method and every method's settings under one flat name each
    (`consensus.*`; each method's own dataclass above holds their defaults, rules and
    documentation), then which frames vote (`num_masks`/`stride`/`selection`) and the fill
    and body rules after it."""

    method: str = "rgc"
    """A registered vote rule: rgc (the paper's), flashsplat or weighted_mean
    (`python -m sagonline plugins vote-rules`)."""
    eps: float = RgcSettings.eps
    """rgc: `RgcSettings.eps`."""
    delta: float | None = RgcSettings.delta
    """rgc: `RgcSettings.delta` (null: no distance rule)."""
    weighting: str = RgcSettings.weighting
    """rgc: `RgcSettings.weighting`."""
    min_votes: int = RgcSettings.min_votes
    """rgc: `RgcSettings.min_votes`."""
    margin: float = RgcSettings.margin
    """rgc: `RgcSettings.margin`."""
    background_slack: float = FlashSplatSettings.background_slack
    """flashsplat: `FlashSplatSettings.background_slack`."""
    threshold: float = WeightedMeanSettings.threshold
    """weighted_mean: `WeightedMeanSettings.threshold`."""
    num_masks: int | None = None
    """How many masks vote (None: all of those `stride` picks)."""
    stride: int = 1
    """Every stride-th mask is a candidate to vote."""
    selection: str = "uniform"
    """Which num_masks of the candidates: uniform (evenly spaced), first, or random (seeded)."""
    seed: int = 0
    """Seeds `selection=random`."""
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
            num_masks=(n is None or n > 0, n, "> 0, or null for all masks"),
            stride=(self.stride >= 1, self.stride, ">= 1"),
            fill=(0 <= self.fill <= 64, self.fill, "in [0, 64] neighbours (0: off)"),
        )
        self.check_reads()
        self.settings()  # the method's own rules

    def reads(self) -> tuple[str, ...]:
        """The settings its method reads (its settings dataclass's fields)."""
        return tuple(f.name for f in fields(VOTE_RULES[self.method].config))

    def check_reads(self) -> None:
        """Refuse a setting the method does not read that differs from its default (it would be
        ignored without a word), and a method setting that is not a `consensus.*` setting."""
        reads, defaults = self.reads(), VoteConfig.__dataclass_fields__
        missing = [name for name in reads if name not in defaults]
        if missing:
            raise ValueError(
                f"consensus.method={self.method!r}: its settings {missing} are not consensus "
                "settings (a vote rule reads settings VoteConfig holds)"
            )
        plugin = VOTE_RULES[self.method]
        for f in fields(plugin.config):
            if f.default is not MISSING and f.default != defaults[f.name].default:
                raise ValueError(
                    f"consensus.method={self.method!r}: its setting {f.name} defaults to "
                    f"{f.default!r}, consensus.{f.name} to {defaults[f.name].default!r} "
                    "(one default per setting: give it VoteConfig's)"
                )
        for f in fields(self):
            if f.name in SELECTION or f.name in reads:
                continue
            if getattr(self, f.name) != defaults[f.name].default:
                raise ValueError(
                    f"consensus.{f.name}={getattr(self, f.name)!r}: the method {self.method} "
                    f"does not read {f.name} (it reads {', '.join(reads) or 'nothing'})"
                )

    def settings(self):
        """Its method's typed settings (`vote.methods`), filled from these."""
        plugin = VOTE_RULES[self.method]
        return plugin.config(**{name: getattr(self, name) for name in self.reads()})

    def method_rule(self) -> typing.Any:
        """The registered method this config names (a `vote.methods.VoteMethod`, built by the
        registry: this module does not import the vote)."""
        plugin = VOTE_RULES[self.method]
        return plugin.build(self.settings())

    @property
    def rule(self) -> VoteRule:
        """The rule the kernels apply, built once from these settings by the method."""
        return self.method_rule().rule(self.settings())


# The settings every method reads: which masks vote, and the fill and body rule after it.
SELECTION = ("method", "num_masks", "stride", "selection", "seed", "fill", "body")


def vote_setting_specs() -> list[SettingSpec]:
    """Every registered method's settings as one list of controls (the command line's vote
    flags, the viewer's vote panel), in VoteConfig's order, each once, its documentation led
    by the methods that read it (`readers`)."""
    readers: dict[str, list[str]] = {}
    specs: dict[str, SettingSpec] = {}
    for method, method_settings in method_specs().items():
        for spec in method_settings:
            specs.setdefault(spec.name, spec)
            readers.setdefault(spec.name, []).append(method)
    order = [f for f in VoteConfig.__dataclass_fields__ if f in specs]
    order += [name for name in specs if name not in order]
    return [
        replace(specs[n], doc=f"{', '.join(readers[n])}: {specs[n].doc}", readers=tuple(readers[n]))
        for n in order
    ]
