"""Stage II on the real captures: the refinement student's answers against the coarse render's.

    python -m bench.runners.student [--captures all] [--sources sam2_tiny]
        [--votes defaults,chosen] [--training-seeds 0] [--set refine.ema_span=60] [--out reports]

The student (`refine=student`, docs/method.md) trains in the background on the segmenter's 2D
masks of the trajectory and then answers every scored view from the view's RGB render and its
coarse label render. For each capture present and fitted (seed 0) and each source, one
real-capture evaluation with the paper's vote defaults and one with the setting the captures
chose leave-one-capture-out (`captures.CHOSEN`), each with the student: the segmenter's own
mIoU, the coarse render's (the vote's) and the student's, on the same views, and how its
training ended. Each run goes to `multirun/real/<capture>/<source>@refine-student[+...]`; a
rerun reads the finished ones. Tables: <out>/student.md and .csv; <out>/student_views.md and
.csv, the student's gain over the coarse render view by view (from each run's per_view.csv),
by angle to the nearest photograph. With more than one training seed (`--training-seeds 0,1,2`:
the student's `refine.seed`, on the same fit, Stage I and teacher masks; 0 is the default runs'
seed), each setting is trained once per seed, in `...@refine-student[+...]+refine.seed-<k>`,
and <out>/student_seeds.md and .csv give each setting's spread over them: how much of a gain
or loss is the training's draw. With `--curve-every 25`, each setting is trained once more to
`--curve-steps` (400) whatever its loss does (`refine.curve_every=25 refine.max_steps=400
refine.patience=400`), its student scored every 25 steps, and <out>/student_curve.md and .csv
set that curve beside where the plateau rule stopped the default training and what it scored:
whether a longer training would have answered better. Each `--set KEY=VALUE` is added to every
run (the student's settings to compare: `--set refine.ema_span=60`, in folders of their own).
With `--spans 15,30,120,240`, each run also keeps averages of the student's weights over those
spans (`refine.scored_spans`), each scored where it stopped beside its answers and its trained
weights: <out>/student_spans.md and .csv, and <out>/student_spans_loo.md and .csv, the span
chosen leave-one-capture-out against the answers' (`refine.ema_span`, default or `--set`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from bench import OUT_HELP, REPORTS, ROOT
from bench.runners import captures
from bench.runners.real import Evaluations
from bench.tables.report import in_percent, weights_lines, write_table
from bench.tables.spans import span_choice, span_row
from bench.tables.views import refined_gain
from sagonline.refine import RefineConfig
from sagonline.score.run_metrics import RunMetrics

STUDENT = ("refine=student",)
VOTES = ("defaults", "chosen")  # the paper's vote and the one chosen leave-one-capture-out
SOURCES = captures.EVERY_MASK_VOTES  # whose every mask votes and trains the student


def settings(source: str, training_seed: int = 0) -> dict[str, tuple[str, ...]]:
    """The vote settings a source is scored with: the paper's defaults and its chosen ones,
    with the student trained from `training_seed` (0: the default, named by no override)."""
    seed = (f"refine.seed={training_seed}",) if training_seed else ()
    return {
        "defaults": (*STUDENT, *seed),
        "chosen": (*STUDENT, *captures.CHOSEN.get(source, ()), *seed),
    }


def curve_setting(setting: tuple[str, ...], every: int, steps: int) -> tuple[str, ...]:
    """`setting` trained to `steps` whatever its loss does, scored every `every` steps."""
    return (
        *setting,
        f"refine.curve_every={every}",
        f"refine.max_steps={steps}",
        f"refine.patience={steps}",
    )


def curve_row(stopped: dict, curve: RunMetrics) -> dict:
    """One setting's line of student_curve: where the plateau rule stopped its default training
    (`stopped`: its line of student.md) and the student's mIoU at each point of the curve
    run (fractions: the table shows them in percent); with a weight average, its trained
    weights' too."""
    points = curve.scene_extra("refine").get("curve") or []
    scored = [p for p in points if p["miou"] is not None]
    return {
        **{k: stopped[k] for k in ("capture", "source", "vote", "training seed")},
        "coarse mIoU": stopped["coarse mIoU"],
        "plateau rule: steps": stopped["steps"],
        "plateau rule: student mIoU": stopped["student mIoU"],
        "best of the curve: step": max(scored, key=lambda p: p["miou"])["step"] if scored else None,
        **{f"step {p['step']} mIoU": p["miou"] for p in points},
        **{  # with refine.ema_span: the trained weights' own answers beside the average's
            f"step {p['step']} trained mIoU": p["miou_trained"]
            for p in points
            if "miou_trained" in p
        },
    }


def row(capture: str, source: str, vote: str, m: RunMetrics, training_seed: int = 0) -> dict:
    """One run's line: the three answers' mIoU (fractions: the table shows them in percent), the
    student's gain over the coarse render in points, and how its training ended."""
    refine = m.scene_extra("refine")
    timings = m.first_scene().get("timings") or m.timings
    gain = None
    if m.refined_miou is not None and m.miou is not None:
        gain = round(100 * (m.refined_miou - m.miou), 2)
    return {
        "capture": capture,
        "source": source,
        "vote": vote,
        "training seed": training_seed,
        "segmenter alone mIoU": m.segmenter_miou,
        "coarse mIoU": m.miou,
        "student mIoU": m.refined_miou,
        "student - coarse, points": gain,
        "training ended": refine.get("status"),
        "steps": refine.get("steps"),
        "train s": round(timings["refine_train_s"], 1) if "refine_train_s" in timings else None,
        "protocol": m.protocol_id,
    }


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(
        prog="python -m bench.runners.student", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--captures", default="all", help="comma-separated, or all (the fitted)")
    ap.add_argument("--sources", default="sam2_tiny", help=f"comma-separated, of {SOURCES}")
    ap.add_argument(
        "--votes", default=",".join(VOTES), help=f"comma-separated, of {', '.join(VOTES)}"
    )
    ap.add_argument(
        "--training-seeds",
        default="0",
        help="comma-separated student seeds (refine.seed) per setting; more than one also "
        "writes <out>/student_seeds.{md,csv}, each setting's spread over them",
    )
    ap.add_argument(
        "--curve-every",
        type=int,
        default=0,
        help="also train each setting to --curve-steps, its student scored every this many "
        "steps: <out>/student_curve.{md,csv} (default 0: no curve)",
    )
    ap.add_argument("--curve-steps", type=int, default=400, help="the curve's length (400)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an override added to every run, e.g. refine.ema_span=60 (repeatable)",
    )
    ap.add_argument(
        "--spans",
        default="",
        help="comma-separated spans of weight averages each run also scores "
        "(refine.scored_spans): <out>/student_spans{,_loo}.{md,csv}",
    )
    ap.add_argument("--out", type=Path, default=REPORTS, help=OUT_HELP)
    args = ap.parse_args(argv)
    if args.curve_every < 0 or args.curve_steps < max(args.curve_every, 1):
        ap.error("--curve-every must be >= 0 and --curve-steps >= 1 and >= --curve-every")
    sources = args.sources.split(",")
    if not set(sources) <= set(SOURCES):
        bad = sorted(set(sources) - set(SOURCES))[0]
        ap.error(f"--sources: {bad!r} is not one of {', '.join(SOURCES)}")
    training_seeds = parse_seeds(args.training_seeds, ap.error)
    spans = parse_seeds(args.spans, ap.error, "--spans") if args.spans else []
    if 0 in spans:
        ap.error("--spans: 0 is the trained weights, scored with any span; give spans >= 1")
    scored = (f"refine.scored_spans=[{','.join(map(str, spans))}]",) if spans else ()
    if bad_sets := [o for o in args.set if "=" not in o.strip("=")]:
        ap.error(f"--set: {bad_sets[0]!r} is not KEY=VALUE")
    votes = args.votes.split(",")
    if not set(votes) <= set(VOTES):
        bad = sorted(set(votes) - set(VOTES))[0]
        ap.error(f"--votes: {bad!r} is not one of {', '.join(VOTES)}")
    names = captures.fitted_named(args.captures, ap.error)
    runs, rows, gains, commands, curves, curve_commands = Evaluations(), [], [], [], [], []
    span_rows, records = [], []  # records: every run read, the curves' too
    for capture in names:
        for source in sources:
            for seed in training_seeds:
                for vote in votes:
                    setting = (*settings(source, seed)[vote], *args.set, *scored)
                    commands.append(" ".join(captures.command(capture, source, 0, setting)))
                    m = runs.run(capture, source, 0, setting)
                    records.append(m)
                    if m is None:
                        continue
                    rows.append(row(capture, source, vote, m, seed))
                    gains.append(view_gains(capture, source, vote, setting, seed))
                    if spans:
                        span_rows.append(span_row(rows[-1], m))
                    if args.curve_every:
                        longer = curve_setting(setting, args.curve_every, args.curve_steps)
                        command = " ".join(captures.command(capture, source, 0, longer))
                        commands.append(command)
                        curve_commands += [commands[-2], command]
                        curve = runs.run(capture, source, 0, longer)
                        records.append(curve)
                        if curve is not None:
                            curves.append(curve_row(rows[-1], curve))
    df = pd.DataFrame(rows)
    built = (
        f"`python -m bench.runners.student --captures {args.captures} --sources {args.sources}"
        f" --votes {args.votes} --training-seeds {args.training_seeds}"
        + (
            f" --curve-every {args.curve_every} --curve-steps {args.curve_steps}"
            if args.curve_every
            else ""
        )
        + "".join(f" --set {o}" for o in args.set)
        + (f" --spans {args.spans}" if spans else "")
        + "`"
    )
    weights = weights_lines(records)  # the masks' model, by file and digest
    notes = [
        "mIoU in percent on every masked view but the reference, fit seed 0; segmenter alone: "
        "its masks' own, on the trajectory's views; coarse: the fused labels rendered (the "
        "vote's answer); student: the refinement student's answer (`refine=student`) from the "
        "view's RGB render and its coarse label render, after training on the segmenter's masks",
        "vote: defaults, the paper's; chosen: `"
        + " ".join(captures.KEPT)
        + "` (chosen leave-one-capture-out, reports/real_captures_loo.md)",
        *weights,
        f"built by {built}; each run:",
        *(f"`python -m bench.runners.eval {c}`" for c in commands),
    ]
    write_table(df, args.out, "student", title="Stage II on the real captures", notes=notes)
    write_table(
        pd.DataFrame(gains),
        args.out,
        "student_views",
        title="Stage II on the real captures, view by view",
        notes=[
            "the student's IoU minus the coarse render's on each scored view, in points (each "
            "run's per_view.csv, its `refined` rows against its `coarse` ones); better / worse: "
            "the views that gain / lose more than 0.1 point; by the angle from the view to the "
            "nearest photograph (at photo: a photographed view): the mean gain and the views",
            f"the runs of student.md ({built})",
        ],
    )
    print(in_percent(df).to_string(index=False))
    if span_rows:
        write_span_tables(pd.DataFrame(span_rows), args.out, built, commands, args.set, weights)
    if len(training_seeds) > 1 and not df.empty:
        spread = seed_spread(df)
        write_table(
            spread,
            args.out,
            "student_seeds",
            title="Stage II on the real captures, over the student's training seeds",
            notes=[
                "each setting of student.md trained once per seed (`refine.seed`), on the same "
                "fit, Stage I labels and teacher masks; mean, min and max over the seeds of the "
                "student's mIoU and of its gain over the coarse render (points); coarse spread: "
                "the coarse render's max - min over the same runs (0: Stage I did not move)",
                *weights,
                f"the runs of student.md, built by {built}",
            ],
        )
        print(in_percent(spread).to_string(index=False))
    if curves:
        table = pd.DataFrame(curves)
        write_table(
            table,
            args.out,
            "student_curve",
            title="Stage II on the real captures, along the student's training",
            notes=[
                "plateau rule: the default training (student.md's run), stopped by the plateau "
                f"rule; step k: the student trained {args.curve_steps} steps whatever its loss "
                f"did (`{' '.join(curve_setting((), args.curve_every, args.curve_steps))}`), "
                "scored every "
                f"{args.curve_every} steps at the same views (step 0: the untrained student, "
                "which answers the coarse render); the training is the same as the default's "
                "up to where that stopped (one seed draws the same batches whatever the rule)",
                *weights,
                f"built by {built}; each run (the default's, then the curve's):",
                *(f"`python -m bench.runners.eval {c}`" for c in curve_commands),
            ],
        )
        print(in_percent(table).to_string(index=False))
    return df


def parse_seeds(text: str, error, option: str = "--training-seeds") -> list[int]:
    """`--training-seeds` (or `option`): distinct non-negative integers, in the order given."""
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        error(f"{option}: {text!r} is not a comma-separated list of integers")
    if any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        error(f"{option}: {text!r} must be distinct integers >= 0")
    return seeds


def write_span_tables(
    df: pd.DataFrame,
    out: Path,
    built: str,
    commands: list[str],
    overrides: list[str],
    weights: list[str],
) -> None:
    """<out>/student_spans (each run's answers from each span's average; `commands`: the
    runs', `weights`: the note lines naming their model's files) and <out>/student_spans_loo
    (the span chosen leave-one-capture-out against the answers' span: `--set
    refine.ema_span=K` among `overrides`, else the default)."""
    given = [o.split("=", 1)[1] for o in overrides if o.startswith("refine.ema_span=")]
    answers = int(given[-1]) if given else RefineConfig().ema_span
    write_table(
        df,
        out,
        "student_spans",
        title="Stage II on the real captures, the student's weights averaged over other spans",
        notes=[
            "each run of student.md kept averages of the student's weights over these spans "
            "(`refine.scored_spans`), updated at every step of the same training, and scored "
            "each where the plateau rule stopped it, at the same views; span k: the average "
            f"over about k steps; span 0: the trained weights; span {answers}: the answers "
            f"(`refine.ema_span={answers}`, whose mIoU is student.md's)",
            *weights,
            f"built by {built}; each run:",
            *(f"`python -m bench.runners.eval {c}`" for c in commands),
        ],
    )
    choice, kept_lines = span_choice(df, answers)
    write_table(
        choice,
        out,
        "student_spans_loo",
        title="Stage II on the real captures, the span chosen leave-one-capture-out",
        notes=[
            "per source and vote: each capture held out in turn, the span of the best mean "
            "mIoU over the other captures (each capture the mean over its training seeds) is "
            f"chosen and reported on it against span {answers}, the answers' (`held out, "
            "chosen`: the leave-one-out figure, percent)",
            *kept_lines,
            f"the runs of student_spans.md, built by {built}",
        ],
    )
    print(in_percent(df).to_string(index=False))
    print(choice.to_string(index=False))


def seed_spread(df: pd.DataFrame) -> pd.DataFrame:
    """One line per (capture, source, vote) of student.md's rows: the student's mIoU and gain
    over the training seeds (mean, min, max), and how far the coarse render moved."""
    lines = []
    for (capture, source, vote), runs in df.groupby(["capture", "source", "vote"], sort=False):
        student, gain = runs["student mIoU"].astype(float), runs["student - coarse, points"]
        coarse = runs["coarse mIoU"].astype(float)
        lines.append(
            {
                "capture": capture,
                "source": source,
                "vote": vote,
                "training seeds": ",".join(map(str, runs["training seed"])),
                "coarse mIoU": coarse.mean(),
                "coarse spread, points": round(100 * (coarse.max() - coarse.min()), 2),
                "student mean mIoU": student.mean(),
                "student min mIoU": student.min(),
                "student max mIoU": student.max(),
                "gain mean, points": round(gain.astype(float).mean(), 2),
                "gain min, points": gain.min(),
                "gain max, points": gain.max(),
                "steps": f"{runs['steps'].min()}-{runs['steps'].max()}",
            }
        )
    return pd.DataFrame(lines)


def view_gains(
    capture: str, source: str, vote: str, setting: tuple[str, ...], training_seed: int = 0
) -> dict:
    """One run's line of student_views: its per-view gains (`views.refined_gain`)."""
    run = ROOT / captures.folder(capture, source, 0, captures.same_scene(capture, 0, setting))
    per_view = run / "per_view.csv"
    found = refined_gain(pd.read_csv(per_view)) if per_view.is_file() else {}
    return {
        "capture": capture,
        "source": source,
        "vote": vote,
        "training seed": training_seed,
        **found,
    }


if __name__ == "__main__":
    main()
