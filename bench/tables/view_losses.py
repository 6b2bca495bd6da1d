"""Where a mask source loses, view by view: the cross-capture table's runs (`bench.runners.real`)
read back, each view's IoU under one source against another's on the same fit.

    python -m bench.tables.view_losses [--captures a,b] [--seeds 0,1,2] [--source sam2_tiny]
                                [--against real] [--setting chosen|defaults] [--worst 5]

For every capture and seed whose two runs are finished, each scored view's IoU under --source
and under --against (per_view.csv), the difference, whether the view was photographed, and
where --source's missed and extra pixels were lost (the fit, the vote, the segmenter:
sagonline/score/diagnosis.py). Prints the --worst views of each capture (largest loss,
averaged over the seeds) and each capture's share of views that lose more than 5 points.
"""

from __future__ import annotations

import argparse

import pandas as pd

from bench import ROOT
from bench.runners.captures import CHOSEN, captures, folder
from sagonline.score.diagnosis import CAUSE_GROUPS


def views(capture: str, source: str, seed: int, chosen: bool) -> pd.DataFrame | None:
    """One run's per_view.csv (its coarse rows), None when the run is not finished."""
    setting = CHOSEN.get(source, ()) if chosen else ()
    path = ROOT / folder(capture, source, seed, setting) / "per_view.csv"
    if not path.is_file():
        return None
    rows = pd.read_csv(path)
    return rows[rows["mode"] == "coarse"] if "mode" in rows else rows


def losses(names, seeds, source, against, chosen) -> pd.DataFrame:
    out = []
    for capture in names:
        for seed in seeds:
            mine, theirs = (views(capture, s, seed, chosen) for s in (source, against))
            if mine is None or theirs is None:
                continue
            both = mine.merge(theirs[["view", "iou"]], on="view", suffixes=("", "_against"))
            both["capture"], both["seed"] = capture, seed
            out.append(both)
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame()


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(
        prog="python -m bench.tables.view_losses", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--captures", help="comma-separated (default: every capture)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--source", default="sam2_tiny")
    ap.add_argument("--against", default="real")
    ap.add_argument("--setting", choices=("chosen", "defaults"), default="chosen")
    ap.add_argument("--worst", type=int, default=5, help="views shown per capture (1-50)")
    args = ap.parse_args(argv)
    if not 1 <= args.worst <= 50:
        ap.error(f"--worst {args.worst}: 1 to 50")
    known = captures()
    names = args.captures.split(",") if args.captures else known
    if set(names) - set(known):
        ap.error(f"--captures: the captures are {', '.join(known)}")
    try:
        seeds = sorted({int(s) for s in args.seeds.split(",")})
    except ValueError:
        ap.error(f"--seeds {args.seeds!r}: comma-separated integers")
    rows = losses(names, seeds, args.source, args.against, args.setting == "chosen")
    if rows.empty:
        raise SystemExit(f"no capture has finished {args.source} and {args.against} runs")
    rows["loss"] = 100 * (rows["iou_against"] - rows["iou"])
    for group, causes in CAUSE_GROUPS.items():  # the missed pixels by where they were lost
        rows[f"missed_by_{group}"] = rows[[c for c in causes if c in rows]].sum(axis=1)
    shown = []
    for capture, part in rows.groupby("capture", sort=False):
        per_view = part.groupby("view").agg(
            loss=("loss", "mean"),
            iou=("iou", "mean"),
            iou_against=("iou_against", "mean"),
            photographed=("photographed", "first"),
            seeds=("seed", "nunique"),
            missed_px=("missed_px", "sum"),
            missed_by_fit=("missed_by_fit", "sum"),
            missed_by_vote=("missed_by_vote", "sum"),
            missed_by_segmenter=("missed_by_segmenter", "sum"),
            extra_px=("extra_px", "sum"),
            extra_by_fit=("extra_fit", "sum"),
            extra_by_segmenter=("extra_segmenter", "sum"),
        )
        share = float((per_view["loss"] > 5).mean())
        print(
            f"\n## {capture}: {args.source} against {args.against} ({args.setting}), "
            f"{len(per_view)} views, {100 * share:.1f}% lose more than 5 points\n"
        )
        worst = per_view.sort_values("loss", ascending=False).head(args.worst).round(3)
        print(worst.to_markdown())
        shown.append(worst.assign(capture=capture))
    return pd.concat(shown)


if __name__ == "__main__":
    main()
