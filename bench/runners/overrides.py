"""A command line's `key=value` overrides checked before Hydra composes them: a key that is no
setting, or a group option that does not exist, is refused in one line naming it (exit 2)."""

from __future__ import annotations

import dataclasses
import re
import sys

from bench import ROOT
from bench.runners.config import EvalConfig, ScenesConfig


def check_override_keys(schema: type, argv: list[str], command: str) -> None:
    """A command line's `key=value` overrides whose first part is no setting of `schema` stop
    here, in one line naming the key (Hydra's own refusal is several lines and exit 1)."""
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
