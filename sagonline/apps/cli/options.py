"""The options `sagonline segment` and `sagonline view` share, declared once: the segmenter
(--segmenter, --checkpoint, --segmenter-option), the vote (--method and each method's settings,
generated from their dataclasses in `vote.methods`) and the label renders' --min-weight, and
what each builds from them. A `--prompts` replay's settings come in as a typed
`recorded.Replay`, never as attributes of the parsed arguments."""

from __future__ import annotations

import argparse
import contextlib
import re
from dataclasses import fields

from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.segment.base import DEFAULT_SEGMENTER


def add_segmenter_arguments(parser, default: str | None = DEFAULT_SEGMENTER) -> None:
    """--segmenter (a registered one; `default`, or None where a --prompts file may name it),
    --checkpoint and --segmenter-option KEY=VALUE."""
    from sagonline.core.plugins import SEGMENTERS

    parser.add_argument(
        "--segmenter",
        default=default,
        choices=SEGMENTERS.names(),
        help=None if default else f"default: {DEFAULT_SEGMENTER}",
    )
    parser.add_argument("--checkpoint", help="the model's local checkpoint (sam2, sam3, yolo)")
    parser.add_argument(
        "--segmenter-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any setting of the segmenter's config (`sagonline plugins segmenters`)",
    )


def add_vote_arguments(parser) -> None:
    """--method, one flag per method setting (its type, choices and help from its field;
    'none' for a setting that can be off), and --body."""
    from sagonline.core.plugins import VOTE_RULES
    from sagonline.vote.settings import vote_setting_specs

    group = parser.add_argument_group("vote (defaults: each method's settings, vote/settings.py)")
    group.add_argument("--method", choices=VOTE_RULES.names() or None)
    for spec in vote_setting_specs():
        kind = optional_number(spec.kind) if spec.optional else spec.kind
        flag = f"--{spec.name.replace('_', '-')}"
        off = "; none: off" if spec.optional else ""
        doc = f"{spec.doc} (default {spec.default}{off})".replace("%", "%%")
        group.add_argument(flag, type=kind, choices=spec.choices, help=doc)
    group.add_argument(
        "--body",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="keep each object's labels on its body (its largest touching cluster; off by "
        "default, not the paper's protocol)",
    )


OFF = "none"
"""What a flag of a setting that may be off is given to turn it off (the setting's null)."""


def optional_number(kind: type):
    """A flag's type for a setting that may be off: a number, or 'none' (OFF)."""

    def parse(text: str):
        return OFF if text.strip().lower() in ("none", "null", "off") else kind(text)

    parse.__name__ = kind.__name__  # argparse names the type in its refusals
    return parse


def vote_config(args, replay=None):
    """The vote's settings: the method's defaults (or the --prompts file's), with what the
    command line gave; a refusal names the flag or the labels.json field."""
    from sagonline.vote.settings import VoteConfig, vote_setting_specs

    recorded = dict(replay.vote) if replay is not None else {}
    names = ["method", "body", *(spec.name for spec in vote_setting_specs())]
    given = {name: getattr(args, name) for name in names}
    given = {k: None if v is OFF else v for k, v in given.items() if v is not None}
    try:
        return VoteConfig(**(recorded | given))
    except ValueError as exc:  # named as the user gave it: a flag, or the labels.json field
        message = str(exc)
        for key in VoteConfig.__dataclass_fields__:
            where = replay.path if replay is not None else "labels.json"
            name = f"--{key.replace('_', '-')}" if key in given else f"{where} vote.{key}"
            message = message.replace(f"consensus.{key}=", f"{name} ")
        raise ValueError(message) from None


def add_min_weight_argument(parser) -> None:
    """--min-weight: the label renders' threshold (`segment` and `view`)."""
    parser.add_argument(
        "--min-weight",
        type=float,
        metavar="W",
        help="a label render's pixel takes a label where labelled Gaussians make up W of it "
        f"(default {LABEL_MIN_WEIGHT}; the real captures' chosen setting: 0.5, with "
        "--method flashsplat --body)",
    )


def segmenter_options(args) -> list[str]:
    """The segmenter's settings the command line gave, as KEY=VALUE items (--checkpoint as the
    plug-in's own key): what labels.json records, so that a replay builds the same segmenter."""
    from sagonline.core.plugins import SEGMENTERS

    names = {f.name for f in fields(SEGMENTERS[args.segmenter].config)}
    items = []
    for option in args.segmenter_option:
        key, sep, value = option.partition("=")
        if not sep:
            raise ValueError(f"--segmenter-option {option!r}: expected KEY=VALUE")
        items.append(f"{key.strip()}={value}")
    if args.checkpoint:
        key = next((k for k in ("checkpoint", "weights") if k in names), None)
        if key is None:
            raise ValueError(f"--checkpoint: segmenter {args.segmenter} takes no checkpoint")
        items.append(f"{key}={args.checkpoint}")
    return items


def build_segmenter(args, prompt, replay=None):
    """The chosen segmenter from the registry, its checkpoint and options applied; refused when
    it cannot read the prompt given (text to a click segmenter, clicks to a text one)."""
    from sagonline.core.plugins import SEGMENTERS

    plugin = SEGMENTERS[args.segmenter]
    names = {f.name for f in fields(plugin.config)}
    values: dict = {
        key: None if value.strip().lower() == "null" else value  # Hydra's spelling of none
        for key, value in (item.split("=", 1) for item in segmenter_options(args))
    }
    if "device" in names:
        values.setdefault("device", args.device)
    with command_line_words():
        segmenter = plugin.build(plugin.settings(values, where=f"segmenter {args.segmenter}"))
    wants = set(getattr(segmenter, "reads", ()))
    given = {"text"} if prompt.texts else {"clicks"}
    if "ground_truth" in wants:
        raise ValueError(
            f"--segmenter {args.segmenter} reads the views' ground truth, which a scene of "
            "one's own does not have"
        )
    if not wants & given:
        what = "text (--text)" if prompt.texts else "clicks and masks"
        reads = ", ".join(sorted(wants)) or "no prompt (it segments automatically)"
        raise ValueError(f"--segmenter {args.segmenter} does not read {what}; it reads {reads}")
    with command_line_words():
        segmenter.check()
    if replay is not None and replay.weights is not None:
        from sagonline.apps.cli.recorded import say_if_other_weights

        say_if_other_weights(replay, segmenter)
    return segmenter


@contextlib.contextmanager
def command_line_words():
    """A segmenter's refusal (ValueError, OSError) as a ValueError in this command line's
    words (`in_command_line_words`): a plug-in names its settings as the evaluation does."""
    try:
        yield
    except (ValueError, OSError) as exc:
        raise ValueError(in_command_line_words(str(exc))) from None


def in_command_line_words(text: str) -> str:
    """A segmenter's message in this command line's words: `segmenter.checkpoint` and
    `segmenter.weights` are --checkpoint, another `segmenter.KEY` is --segmenter-option KEY,
    and `segmenter=NAME` is --segmenter NAME (the evaluation's Hydra spellings)."""
    text = re.sub(r"\bsegmenter\.(?:checkpoint|weights)=", "--checkpoint ", text)
    text = re.sub(r"\bsegmenter\.(?:checkpoint|weights)\b", "--checkpoint", text)
    text = re.sub(r"\bsegmenter\.(\w+)", r"--segmenter-option \1", text)
    return re.sub(r"(?<![-.\w])segmenter=(\w+)", r"--segmenter \1", text)


def label_min_weight(args, replay=None) -> float:
    """The label renders' min_weight: --min-weight, else the --prompts file's, else the
    default; checked by the pipeline's rule (named as the user gave it)."""
    from sagonline.pipeline.settings import LabelRenderSettings

    given = args.min_weight
    weight = given if given is not None else (replay.min_weight if replay else None)
    weight = LABEL_MIN_WEIGHT if weight is None else weight
    try:
        LabelRenderSettings(min_weight=weight)
    except ValueError as exc:
        recorded = f"{replay.path if replay else 'labels.json'} label_render.min_weight="
        name = "--min-weight " if given is not None else recorded
        raise ValueError(str(exc).replace("label_render.min_weight=", name)) from None
    return float(weight)
