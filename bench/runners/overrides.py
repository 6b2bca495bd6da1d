"""A command line's `key=value` overrides checked before Hydra composes them: a key that is no
setting, or a group option that does not exist, is refused in one line naming it (exit 2)."""

from __future__ import annotations

import dataclasses
import difflib
import re
import sys
import types
import typing
from collections.abc import Mapping
from typing import Any

from omegaconf import OmegaConf

from bench import ROOT
from bench.runners.config import EvalConfig, ScenesConfig

# Hydra's options that take a value (the next word, unless written `--option=value`), and the
# words `--info` takes as its optional one (hydra/_internal/utils.py, `get_args_parser`)
VALUE_OPTIONS = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name"}
VALUE_OPTIONS |= {"-cn", "--config-dir", "-cd", "--experimental-rerun"}
INFO_WORDS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}


def options_first(argv: list[str]) -> list[str]:
    """`argv` with Hydra's options (and their values) before the overrides, each in its order:
    Hydra's parser takes no override after an option that follows one (`dataset=x --multirun
    a=1,2`: "unrecognized arguments"), which `make eval ARGS="--multirun ..."` writes."""
    options: list[str] = []
    overrides: list[str] = []
    words = iter(argv)
    for word in words:
        if not word.startswith("-"):
            overrides.append(word)
            continue
        options.append(word)
        takes = word in VALUE_OPTIONS or word in ("--info", "-i")
        value = next(words, None) if takes else None
        if value is None:
            continue
        if word in VALUE_OPTIONS or value in INFO_WORDS:
            options.append(value)
        else:  # --info without a value: the word after it is an override
            overrides.append(value)
    return options + overrides


def check_override_keys(schema: type, argv: list[str], command: str) -> None:
    """A command line's `key=value` overrides whose first part is no setting of `schema`, or
    whose later parts are none of the node they name (`check_nested_keys`), stop here, in one
    line naming the key (Hydra's own refusal is several lines and exit 1)."""
    known = {f.name for f in dataclasses.fields(schema)} | {"hydra"}
    for arg in argv:
        if arg.startswith(("-", "+", "~")) or "=" not in arg:
            continue
        key, value = arg.split("=", 1)
        top = re.split(r"[./@]", key, maxsplit=1)[0]  # hydra/launcher=joblib: a Hydra group
        if "." not in key and top in GROUPS and "," not in value:
            options = group_options(top)
            if value not in options | {"schema"}:
                print(
                    f"error: {command}: {arg}: no such {top} option; the options: "
                    f"{', '.join(sorted(options))}",
                    file=sys.stderr,
                )
                raise SystemExit(2)
        if top not in known:
            other = (
                "ScenesConfig's (python -m bench.runners.scenes)"
                if schema is EvalConfig
                else ("EvalConfig's (python -m bench.runners.eval)")
            )
            hint = f"; it is {other}" if top in _fields_of_other(schema) else ""
            print(f"error: {command}: no setting {top!r} (in {arg!r}){hint}", file=sys.stderr)
            raise SystemExit(2)
    check_nested_keys(schema, argv, command)


# Config groups whose options are the registries' keys and the YAML files of conf/<group>/.
GROUPS = ("segmenter", "dataset", "consensus", "renderer", "refine", "feedback", "fit")


def group_options(group: str) -> set[str]:
    from sagonline.core.plugins import DATASETS, SEGMENTERS, VOTE_RULES

    registry = {"segmenter": SEGMENTERS, "dataset": DATASETS, "consensus": VOTE_RULES}.get(group)
    files = {p.stem for p in (ROOT / "conf" / group).glob("*.yaml")}
    return files | set(registry.keys() if registry is not None else [])


def _fields_of_other(schema: type) -> set[str]:
    other = ScenesConfig if schema is EvalConfig else EvalConfig
    return {f.name for f in dataclasses.fields(other)}


def check_nested_keys(schema: type, argv: list[str], command: str) -> None:
    """`section.key=value` overrides (`+` or not) whose key is no setting of the node it names,
    a typed section's (consensus.*, fit.*, ...) or the chosen segmenter's or dataset's config's,
    and values that are not the number or true / false their setting holds, stop here in one
    line naming the key and the nearest setting (Hydra's refusal is several lines, and for a key
    suggests a `+`, which `refuse_unknown_keys` refuses next)."""
    chosen = chosen_options(schema, argv)
    root = dataclass_settings(schema)
    root |= {g: plugin_settings(g, chosen) for g in PLUGIN_GROUPS if g in root}
    for arg in argv:
        if arg.startswith(("-", "~")) or "=" not in arg or arg.startswith("hydra"):
            continue
        key, value = arg.lstrip("+").split("=", 1)
        parts, settings = key.split("."), root
        for depth, part in enumerate(parts):
            if not isinstance(settings, dict):
                break
            if part not in settings:  # a first part: check_override_keys said so already
                _refuse_key(command, key, depth, settings, chosen)
            settings = settings[part]
        if (
            isinstance(settings, type)
            and settings in VALUE_WORDS
            and not _reads_as(value, settings)
        ):
            print(f"error: {command}: {arg}: must be {VALUE_WORDS[settings]}", file=sys.stderr)
            raise SystemExit(2)


def _refuse_key(command: str, key: str, depth: int, settings: dict, chosen: dict) -> None:
    parts = key.split(".")
    where = ".".join(parts[:depth])
    of = f" of {where} {chosen[where]}" if where in PLUGIN_GROUPS and chosen.get(where) else ""
    near = difflib.get_close_matches(parts[depth], list(settings), n=1)
    hint = f"; did you mean {where}.{near[0]}?" if near else ""
    listed = "" if near else f"; its settings: {', '.join(sorted(settings))}"
    print(f"error: {command}: {key}: no such setting{of}{hint}{listed}", file=sys.stderr)
    raise SystemExit(2)


Settings = dict[str, Any]  # setting -> its own Settings, or its type where it holds a value
PLUGIN_GROUPS = ("segmenter", "dataset")


def plugin_settings(group: str, chosen: dict[str, str | None]) -> Settings | None:
    """The settings of the chosen plug-in's node (its config's and the node's own keys); None
    where the option is not known here (Hydra checks it as it composes), or where a plug-in
    cannot be loaded (`register_schemas_or_exit` says why, in one line)."""
    from sagonline.core.plugins import DATASETS, NODE_KEYS, SEGMENTERS, PluginError

    registry = SEGMENTERS if group == "segmenter" else DATASETS
    try:
        kind = plugin_kind(group, chosen.get(group), registry)
        if kind is None:
            return None
        own = dataclass_settings(registry[kind].config)
    except PluginError:
        return None
    if group == "segmenter":
        return {**own, **dict.fromkeys(NODE_KEYS, str)}
    return {"kind": str, "name": str, "root": str, "adapter": own}


VALUE_WORDS = {int: "an integer", float: "a number", bool: "true or false"}


def _reads_as(value: str, kind: type) -> bool:
    """Whether a command line's value reads as `kind` (int, float, or bool: only the words
    true and false, in any case, as `config.check_boolean_overrides` holds them), or is more
    than a value (a sweep, an interpolation, null), which Hydra reads."""
    if value == "null" or any(c in value for c in ",()[]${}"):
        return True
    if kind is bool:
        return value.strip().lower() in ("true", "false")
    try:
        kind(value)
    except ValueError:
        return False
    return True


def chosen_options(schema: type, argv: list[str]) -> dict[str, str | None]:
    """The option each plug-in group runs with: the command line's `group=option`, else the
    default its conf/*.yaml picks; None where a sweep names several."""
    conf = "eval" if schema is EvalConfig else "scenes"
    picked: dict[str, str | None] = {}
    for entry in OmegaConf.load(ROOT / "conf" / f"{conf}.yaml").get("defaults", []):
        if isinstance(entry, Mapping):
            picked.update({str(k): str(v) for k, v in entry.items()})
    for arg in argv:
        key, _, value = arg.lstrip("+").partition("=")
        if key in PLUGIN_GROUPS:
            picked[key] = None if "," in value or "(" in value else value
    return picked


def plugin_kind(group: str, option: str | None, registry) -> str | None:
    """The registry key an option of `group` builds: the option itself, or the one a preset in
    conf/<group>/ names first in its defaults (None: not known)."""
    seen: set[str] = set()
    while option is not None and option not in registry and option not in seen:
        seen.add(option)
        preset = ROOT / "conf" / group / f"{option}.yaml"
        if not preset.is_file():
            return None
        first = [d for d in OmegaConf.load(preset).get("defaults", []) if d != "_self_"]
        option = str(first[0]) if first and isinstance(first[0], str) else None
    return option if option in registry else None


def dataclass_settings(kind: Any) -> Any:
    """A dataclass's fields, each with its own settings where it is a dataclass, else its type
    (`X | None` is X's: `null` always reads; another union is no one type: None); `kind`
    itself where it is no dataclass."""
    args = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        kind = rest[0] if len(rest) == 1 else None
    if not (isinstance(kind, type) and dataclasses.is_dataclass(kind)):
        return kind if isinstance(kind, type) else None
    hints = typing.get_type_hints(kind)
    return {f.name: dataclass_settings(hints.get(f.name)) for f in dataclasses.fields(kind)}
