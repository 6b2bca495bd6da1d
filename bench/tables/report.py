"""Gather run directories into `reports/`: Markdown and CSV tables, scores in percent.

    python -m bench.tables.report [RUN_DIR_OR_ROOT ...] [--out reports]  # runs.*, scenes.*
    python -m bench.tables.report --fits  # fits.*, fit_*_heldout.jpg
    python -m bench.tables.report --views NAME RUN ...  # NAME.*, NAME_iou_vs_angle.png

Every `metrics.json` below the given folders (default: runs/ and multirun/) becomes one row of
`reports/runs.{md,csv}` and one row per scene of `reports/scenes.{md,csv}`; runs whose results
and settings are identical (a run copied, or repeated) are one row that counts them. Each table
states the device, torch version and resize rule of its rows. Nothing else in `reports/` is
written unless asked: `--fits` tabulates every `fit_metrics.json` written by `make scenes`
(under scenes/ and datasets/), `--views` one capture's views by kind.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from bench import OUT_HELP, REPORTS
from bench.runners.rundir import read_run_metrics
from bench.tables.fits import write_fits
from bench.tables.views import plot_iou_against_angle, view_rows
from sagonline.core.files import atomic_write_text
from sagonline.score.run_metrics import RunMetrics

ROOT = Path(__file__).resolve().parents[2]


def find_runs(roots: list[Path]) -> dict[Path, RunMetrics]:
    """Run folder -> its record, for the folders whose metrics.json reads (a bad one is named on
    stderr and skipped), sorted by folder."""
    found = sorted({p.parent for r in roots if r.exists() for p in r.rglob("metrics.json")})
    records = {run: read_run_metrics(run / "metrics.json") for run in found}
    return {run: m for run, m in records.items() if m is not None}


def device_text(dev: dict) -> str:
    hw = dev.get("gpu") or f"{dev.get('cpu', '?')} x{dev.get('cpu_cores', '?')}"
    return f"{hw}, torch {dev.get('torch', '?')}"


def run_rows(runs: dict[Path, RunMetrics]) -> tuple[pd.DataFrame, pd.DataFrame]:
    runs_rows, scene_rows = [], []
    for run, m in runs.items():
        c = m.consensus
        base = {
            "run": str(run.relative_to(ROOT)) if run.is_relative_to(ROOT) else str(run),
            "dataset": m.dataset,
            "protocol": m.protocol_id or f"{m.dataset}/unversioned",
            "segmenter": m.segmenter,
            "method": c.get("method"),
            "eps": c.get("eps"),
            "delta": c.get("delta"),
            "min_votes": c.get("min_votes"),
            "margin": c.get("margin"),
            "num_masks": c.get("num_masks"),
            "overrides": " ".join(m.overrides),
        }
        l3 = [s["labels3d"]["accuracy"] for s in m.scenes if s.get("labels3d")]
        vote_ms, vote_cached = m.vote_ms_per_mask()
        runs_rows.append(
            {
                **base,
                "mIoU": m.miou,
                "mAcc": m.macc,
                "segmenter_mIoU": m.segmenter_miou,
                "refined_mIoU": m.refined_miou,
                "labels3d_acc": sum(l3) / len(l3) if l3 else None,
                "vote_ms_per_mask": None if vote_cached else vote_ms,
                "cached_vote_ms_per_mask": vote_ms if vote_cached else None,
                "partial": m.partial,
                "re-scored": rescore_words(run),
                "device": device_text(m.device),
                "resize": m.resize_rule,
            }
        )
        for s in m.scenes:
            l3s = s.get("labels3d") or {}
            scene_rows.append(
                {
                    **base,
                    "scene": s["scene"],
                    "status": s.get("status"),
                    "mIoU": s.get("miou"),
                    "mAcc": s.get("macc"),
                    "segmenter_mIoU": s.get("segmenter_miou"),
                    "labels3d_acc": l3s.get("accuracy"),
                    "labels3d_coverage": l3s.get("coverage"),
                    **{k: v for k, v in s.get("timings", {}).items()},
                    "error": s.get("error"),
                }
            )
    return pd.DataFrame(runs_rows), pd.DataFrame(scene_rows)


def score_columns(df: pd.DataFrame) -> list[str]:
    """The columns that hold scores (fractions in metrics.json and per_view.csv)."""
    return [c for c in df.columns if c.endswith(("mIoU", "mAcc", "_acc", "_coverage"))]


def in_percent(df: pd.DataFrame) -> pd.DataFrame:
    """The table with its scores in percent, rounded to 0.01 (what every report shows)."""
    shown = df.copy()
    for c in score_columns(df):
        shown[c] = (100 * pd.to_numeric(shown[c], errors="coerce")).round(2)
    return shown


TIMING_HINTS = ("_s", "_ms", "ms_per", "seconds", "per_frame", "per_mask")


def merge_identical(df: pd.DataFrame) -> pd.DataFrame:
    """Rows that differ only in their run folder and timings are one row: `runs` counts them,
    `run` names the first (+ how many more), each timing is the median of those that have one."""
    if df.empty:
        return df.assign(runs=pd.Series(dtype=int))
    timing = [c for c in df.columns if c != "run" and any(h in c for h in TIMING_HINTS)]
    key = [c for c in df.columns if c not in ("run", *timing)]
    filled = df[key].astype(object).where(df[key].notna(), "\0none")
    groups = filled.astype(str).agg("\x1f".join, axis=1)
    rows = []
    for _, index in df.groupby(groups, sort=False).groups.items():
        part = df.loc[index]
        row = part.iloc[0].copy()
        row["runs"] = len(part)
        if len(part) > 1:
            row["run"] = f"{row['run']} (+{len(part) - 1} identical)"
        for c in timing:
            values = pd.to_numeric(part[c], errors="coerce").dropna()
            row[c] = float(values.median()) if len(values) else float("nan")  # a number column
        rows.append(row)
    merged = pd.DataFrame(rows, columns=[*df.columns, "runs"]).reset_index(drop=True)
    return merged[["run", "runs", *[c for c in df.columns if c != "run"]]]


def cell_text(value):
    """A table cell as Markdown reads it: `|` escaped, line breaks as spaces (a field of a
    metrics.json, an override or an error message, must not break the table's rows)."""
    if not isinstance(value, str):
        return value
    return " ".join(value.splitlines()).replace("|", "\\|")


def percent_words(value) -> str:
    """A recorded fraction (metrics.json's 0-1) in percent as the tables show it; what is not a
    number, as it was written."""
    return f"{100 * value:.2f}" if isinstance(value, int | float) else repr(value)


def rescore_words(run: Path) -> str:
    """Whether the run's recorded mIoU / mAcc are what its own label maps give again
    (`sagonline.score.rescore.rescore_run`): `matches`, `CONTRADICTED (...)`, or why it cannot be
    said."""
    from sagonline.core.errors import DatasetError
    from sagonline.score.rescore import rescore_run

    try:
        again = rescore_run(run)
    except (DatasetError, OSError, ValueError) as exc:
        return f"cannot re-score: {exc}"
    if again is None:
        return "no label maps"
    bad = [
        f"{name} recorded {percent_words(value)}, re-scored {100 * rescored:.2f}"
        for name, (value, rescored, ok) in again["checks"].items()
        if not ok
    ]
    if bad:
        print(
            f"warning: {run}/metrics.json is contradicted by its own label maps: " + "; ".join(bad),
            file=sys.stderr,
        )
        return "CONTRADICTED (" + "; ".join(bad) + ")"
    return "matches" if again["checks"] else "nothing recorded to compare"


def weights_lines(records: Iterable[RunMetrics | None]) -> list[str]:
    """A note line per model-backed source among `records` naming the weights its runs read
    (each file and the first 12 hex digits of its sha256, from metrics.json's
    `segmenter_info`); where its runs read different files, each set with its count of runs,
    and runs that recorded no digest counted. Sources without weights add nothing."""
    seen: dict[str, Counter] = {}
    for m in records:
        if m is None:
            continue
        info = m.segmenter_info or {}
        files = tuple(
            f"{Path(str(info.get(key.removesuffix('_sha256'), key))).name} {str(digest)[:12]}"
            for key, digest in sorted(info.items())
            if key.endswith("_sha256")
        )
        if files or m.segmenter_weights:
            seen.setdefault(str(m.segmenter), Counter())[files] += 1

    def runs(n: int) -> str:
        return f"({n} run{'s' * (n > 1)})"

    lines = []
    for source, sets in sorted(seen.items()):
        named = {f: n for f, n in sets.items() if f}
        parts = [", ".join(f) + ("" if len(sets) == 1 else f" {runs(n)}") for f, n in named.items()]
        if unnamed := sets.get((), 0):
            parts.append(f"no digest recorded {runs(unnamed)}")
        lead = f"{source}'s weights" + (" DIFFER between runs" if len(named) > 1 else "")
        lines.append(f"{lead} (file, sha256): " + "; ".join(parts))
    return lines


def to_markdown(df: pd.DataFrame, title: str, notes: list[str]) -> str:
    """A titled Markdown table with its notes (the frame's scores already in percent)."""
    shown = df.copy()
    for c in score_columns(df):
        shown[c] = shown[c].map(lambda v: f"{v:.2f}" if pd.notna(v) else "-")
    shown = shown.astype(object).where(shown.notna(), "-")  # a missing value reads "-", not nan
    shown = shown.map(cell_text)
    body = shown.to_markdown(index=False, floatfmt=".4g")
    return f"# {title}\n\n" + "".join(f"- {n}\n" for n in notes) + "\n" + body + "\n"


def write_table(df: pd.DataFrame, out: Path, stem: str, title: str, notes: list[str]) -> None:
    """`stem`.csv and `stem`.md in `out`, both with the scores in percent."""
    shown = in_percent(df)
    atomic_write_text(out / f"{stem}.csv", shown.to_csv(index=False))
    atomic_write_text(out / f"{stem}.md", to_markdown(shown, title, notes))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        prog="python -m bench.tables.report", description=__doc__.split("\n")[0]
    )
    ap.add_argument("roots", nargs="*", type=Path)
    ap.add_argument("--out", type=Path, default=REPORTS, help=OUT_HELP)
    ap.add_argument(
        "--views",
        metavar="NAME",
        help="only the per-view table and plot of the given runs (captures with photographs "
        "for some views): reports/NAME.{md,csv} and reports/NAME_iou_vs_angle.png",
    )
    ap.add_argument(
        "--fits",
        action="store_true",
        help="also (or, without folders, only) reports/fits.{md,csv} and the held-out renders",
    )
    args = ap.parse_args(argv)
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out {args.out}: a file, not a folder")
    if args.views:
        table, per_view = view_rows(find_runs(args.roots))
        if table.empty:
            raise SystemExit("no run with photographed / mask-only views among those given")
        notes = [
            "mIoU in percent over the views of each kind; the angle is between the optical axes "
            "of a view and of its nearest photographed view.",
            "run: segmenter and the overrides of the run (metrics.json has the full config).",
        ]
        write_table(table, args.out, args.views, f"{args.views}: views by kind", notes)
        plot_iou_against_angle(per_view, args.out / f"{args.views}_iou_vs_angle.png")
        print(table.to_string(index=False))
        return
    if args.fits:
        write_fits(args.out)
        if not args.roots:
            return
    roots = args.roots or [ROOT / "runs", ROOT / "multirun"]
    runs = find_runs(roots)
    if not runs:
        print(f"no runs found under {', '.join(map(str, roots))}: run `make eval` first")
        return
    runs_df, scenes_df = (merge_identical(df) for df in run_rows(runs))
    notes = [
        "mIoU / mAcc in percent: mean over views, then over scenes.",
        "Resize rule and device are per row; runs: how many run folders gave this row (identical "
        "settings and results; timings are their median).",
        "re-scored: whether the recorded mIoU / mAcc are what the run's own label maps give "
        "again (`sagonline score RUN`); CONTRADICTED rows are not results.",
        "cached_vote_ms_per_mask: a run whose votes were all served from the stage cache has no "
        "vote time of its own; this is the mean time of the runs that filled the cache.",
    ]
    write_table(runs_df, args.out, "runs", "Runs", notes)
    write_table(scenes_df, args.out, "scenes", "Scenes", notes)
    shown = in_percent(runs_df).drop(columns=["run", "device", "resize", "overrides"])
    print(shown.to_string(index=False))
    print(
        f"\n{len(runs)} runs ({len(runs_df)} rows) -> {args.out}/runs.md, runs.csv, scenes.md, "
        "scenes.csv"
    )


if __name__ == "__main__":
    main()
