"""The options `sagonline segment` and `sagonline view` share, declared once: the segmenter
(--segmenter, --checkpoint, --segmenter-option) and the label renders' --min-weight, and what
each builds from them."""

from __future__ import annotations

from dataclasses import fields

from sagonline.render.api import LABEL_MIN_WEIGHT
from sagonline.segment.base import DEFAULT_SEGMENTER


def add_segmenter_arguments(parser, default: str | None = DEFAULT_SEGMENTER) -> None:
    """--segmenter (a registered one; `default`, or None where a --prompts file may name it),
    --checkpoint and --segmenter-option KEY=VALUE."""
    from sagonline.core.plugins import SEGMENTERS

    parser.add_argument(
        "--segmenter",
        default=default,
        choices=SEGMENTERS.keys(),
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


def build_segmenter(args, prompt):
    """The chosen segmenter from the registry, its checkpoint and options applied; refused when
    it cannot read the prompt given (text to a click segmenter, clicks to a text one)."""
    from sagonline.core.plugins import SEGMENTERS

    plugin = SEGMENTERS[args.segmenter]
    names = {f.name for f in fields(plugin.config)}
    values: dict = dict(item.split("=", 1) for item in segmenter_options(args))
    if "device" in names:
        values.setdefault("device", args.device)
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
    segmenter.check()
    if getattr(args, "recorded_weights", None) is not None:
        from sagonline.apps.cli.recorded import say_if_other_weights

        say_if_other_weights(args, segmenter)
    return segmenter


def label_min_weight(args) -> float:
    """The label renders' min_weight: --min-weight, else the --prompts file's, else the
    default; checked by the pipeline's rule (named as the user gave it)."""
    from sagonline.pipeline.settings import PipelineSettings

    given = args.min_weight
    weight = given if given is not None else getattr(args, "recorded_min_weight", None)
    weight = LABEL_MIN_WEIGHT if weight is None else weight
    try:
        PipelineSettings(label_min_weight=weight)
    except ValueError as exc:
        recorded = f"{getattr(args, 'prompts', None)} label_render.min_weight="
        name = "--min-weight " if given is not None else recorded
        raise ValueError(str(exc).replace("label_render.min_weight=", name)) from None
    return float(weight)
