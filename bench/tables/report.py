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
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image

from bench import OUT_HELP, REPORTS
from bench.runners.rundir import read_run_metrics
from sagonline.core.files import atomic_write_image, atomic_write_text
from sagonline.datasets.common import SCENES_ROOT
from sagonline.fitting import FitConfig

ROOT = Path(__file__).resolve().parents[2]
# per_view.csv's rows of the fused labels rendered ("coarse"; runs before the name was given
# one meaning called them "initial", which is Table II's 2D segmenter on a novel view)
COARSE = ("coarse", "initial")


def find_runs(roots: list[Path]) -> list[Path]:
    """Run folders whose metrics.json reads (a bad one is named on stderr and skipped)."""
    found = sorted({p.parent for r in roots if r.exists() for p in r.rglob("metrics.json")})
    return [run for run in found if read_run_metrics(run / "metrics.json") is not None]


def load(run: Path) -> dict:
    return json.loads((run / "metrics.json").read_text())


def device_text(dev: dict) -> str:
    hw = dev.get("gpu") or f"{dev.get('cpu', '?')} x{dev.get('cpu_cores', '?')}"
    return f"{hw}, torch {dev.get('torch', '?')}"


def run_rows(runs: list[Path]) -> tuple[pd.DataFrame, pd.DataFrame]:
    runs_rows, scene_rows = [], []
    for run in runs:
        m = load(run)
        c = m.get("consensus", {})
        base = {
            "run": str(run.relative_to(ROOT)) if run.is_relative_to(ROOT) else str(run),
            "dataset": m.get("dataset"),
            "protocol": m.get("protocol_id") or f"{m.get('dataset')}/unversioned",
            "segmenter": m.get("segmenter"),
            "method": c.get("method"),
            "eps": c.get("eps"),
            "delta": c.get("delta"),
            "min_votes": c.get("min_votes"),
            "margin": c.get("margin"),
            "num_masks": c.get("num_masks"),
            "overrides": " ".join(m.get("overrides", [])),
        }
        l3 = [s["labels3d"]["accuracy"] for s in m.get("scenes", []) if s.get("labels3d")]
        runs_rows.append(
            {
                **base,
                "mIoU": m.get("miou"),
                "mAcc": m.get("macc"),
                "segmenter_mIoU": m.get("segmenter_miou"),
                "refined_mIoU": m.get("refined_miou"),
                "labels3d_acc": sum(l3) / len(l3) if l3 else None,
                "vote_ms_per_mask": m.get("timings", {}).get("vote_ms_per_mask"),
                "partial": m.get("partial"),
                "re-scored": rescore_words(run),
                "device": device_text(m.get("device", {})),
                "resize": m.get("resize_rule"),
            }
        )
        for s in m.get("scenes", []):
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


FIT_COLUMNS = [
    "dataset",
    "scene",
    "kind",
    "recipe",
    "init",
    "resolution",
    "images",
    "iterations",
    "gaussians",
    "fit_seconds",
    "psnr_train",
    "psnr_heldout",
    "psnr_heldout_object",
    "heldout_views",
    "folder",
]


def fit_recipe(cfg: dict) -> str:
    """The fit settings that differ from today's defaults ("default" if none), the automatic
    camera clearance and the device left out; settings newer than the fit are named after
    "predates:" (the fit ran without them)."""
    defaults = {
        k: v for k, v in asdict(FitConfig()).items() if k not in ("camera_clearance", "device")
    }
    changed = [
        f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
        for k, v in cfg.items()
        if k in defaults
        and v != defaults[k]
        and not (isinstance(v, list) and tuple(v) == defaults[k])
    ]
    missing = [k for k in defaults if k not in cfg]
    if missing:
        changed.append("predates: " + " ".join(missing))
    return " ".join(changed) or "default"


def fit_rows(roots: list[Path]) -> pd.DataFrame:
    """One row per fitted scene: its fit_metrics.json, and the kind and recipe from
    fit_config.json."""
    rows = []
    for path in sorted({p for r in roots if r.exists() for p in r.rglob("fit_metrics.json")}):
        m = json.loads(path.read_text())
        cfg_path = path.with_name("fit_config.json")
        cfg = json.loads(cfg_path.read_text()) if cfg_path.is_file() else {}
        folder = path.parent
        rows.append(
            {
                **{k: m.get(k) for k in FIT_COLUMNS},
                "scene": folder.parent.name,  # the folder holding gaussians/ (copies rename it)
                "kind": cfg.get("kind"),
                "recipe": fit_recipe(cfg),
                "resolution": "x".join(map(str, m.get("resolution", []))),
                "heldout_views": " ".join(m.get("heldout_views", [])),
                "folder": str(folder.relative_to(ROOT))
                if folder.is_relative_to(ROOT)
                else str(folder),
            }
        )
    return pd.DataFrame(rows, columns=FIT_COLUMNS)


def stack_heldout_renders(folder: Path, out: Path) -> Path | None:
    """The held-out render | photo pairs `make scenes` wrote, stacked into one JPEG in `out`."""
    pairs = sorted(folder.glob("heldout_*.png"))
    if not pairs:
        return None
    rows = [np.asarray(Image.open(p).convert("RGB")) for p in pairs]
    width = min(r.shape[1] for r in rows)
    metrics = json.loads((folder / "fit_metrics.json").read_text())
    name = f"fit_{metrics.get('dataset', 'scene')}_{folder.parent.name}"
    return atomic_write_image(
        out / f"{name}_heldout.jpg", np.concatenate([r[:, :width] for r in rows])
    )


ANGLE_BINS = [-0.5, 0.5, 10, 20, 30, 180]  # degrees to the nearest photograph
ANGLE_LABELS = ["photographed", "0-10", "10-20", "20-30", ">30"]


def view_rows(runs: list[Path]) -> tuple[pd.DataFrame, dict[str, pd.DataFrame]]:
    """Per run (of a capture with photographs for some views): mIoU over the photographed views
    and over the mask-only ones, over the views whose masks did not vote, and by viewing angle
    to the nearest photograph; plus each run's per-view rows keyed by its label."""
    rows, per_view = [], {}
    for run in runs:
        views = pd.read_csv(run / "per_view.csv")
        views = views[views["mode"].isin(COARSE)]
        if "photo_angle_deg" not in views:
            continue
        m = load(run)
        label = " ".join([m.get("segmenter", "?"), *m.get("overrides", [])])
        per_view[label] = views.assign(_overrides=[m.get("overrides", [])] * len(views))
        photo = views["photographed"].astype(bool)
        by_angle = pd.cut(views["photo_angle_deg"], ANGLE_BINS, labels=ANGLE_LABELS)
        row = {
            "run": label,
            "views": len(views),
            "mIoU": views["iou"].mean(),
            "photographed_mIoU": views.loc[photo, "iou"].mean(),
            "photographed_views": int(photo.sum()),
            "mask_only_mIoU": views.loc[~photo, "iou"].mean(),
            "mask_only_views": int((~photo).sum()),
            "not_voted_mIoU": views.loc[~views["voted"].astype(bool), "iou"].mean(),
        }
        for name, group in views.groupby(by_angle, observed=False)["iou"]:
            key = f"{name} deg" if name != "photographed" else "at photo"
            row[f"{key} mIoU"], row[f"{key} views"] = group.mean(), len(group)
        rows.append(row)
    return pd.DataFrame(rows), per_view


def short_labels(overrides: dict[str, list[str]]) -> dict[str, str]:
    """A legend entry per run: only the overrides that differ between the runs shown, each key
    by its last part (`dataset.adapter.exclude_reference=true` -> `exclude_reference=true`);
    the full label where two would read the same."""
    shared = set.intersection(*(set(o) for o in overrides.values())) if overrides else set()
    short = {}
    for label, items in overrides.items():
        parts = [label.split(" ")[0]]  # the segmenter
        for item in items:
            if item in shared or item.startswith(("hydra.", "progress=", "record=")):
                continue
            key, sep, value = item.partition("=")
            parts.append(f"{key.rsplit('.', 1)[-1]}{sep}{value}")
        short[label] = " ".join(parts)
    if len(set(short.values())) < len(short):
        return {label: label for label in overrides}
    return short


def plot_iou_against_angle(per_view: dict[str, pd.DataFrame], path: Path) -> Path:
    """Scatter of per-view IoU (%) against the angle to the nearest photograph, one colour per
    run, the legend (short labels) beside the plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = short_labels(
        {
            label: list(v["_overrides"].iloc[0]) if "_overrides" in v and len(v) else []
            for label, v in per_view.items()
        }
    )
    fig, ax = plt.subplots(figsize=(9, 4.2), dpi=120)
    for label, views in per_view.items():
        ax.scatter(
            views["photo_angle_deg"], 100 * views["iou"], s=12, alpha=0.7, label=names[label]
        )
    ax.set_xlabel("viewing angle to the nearest photograph (degrees; 0: a photographed view)")
    ax.set_ylabel("IoU (%)")
    ax.set_ylim(0, 101)
    ax.grid(alpha=0.3)
    ax.legend(
        fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        borderaxespad=0,
        title="run",
        title_fontsize=8,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_image(path, np.asarray(_figure_rgb(fig)))
    plt.close(fig)
    return path


def _figure_rgb(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3]


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
            row[c] = float(values.median()) if len(values) else None
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
    (`bench.tables.score.rescore_run`): `matches`, `CONTRADICTED (...)`, or why it cannot be
    said."""
    from bench.tables.score import rescore_run
    from sagonline.core.errors import DatasetError

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
        "again (`python -m bench.tables.score RUN`); CONTRADICTED rows are not results.",
    ]
    write_table(runs_df, args.out, "runs", "Runs", notes)
    write_table(scenes_df, args.out, "scenes", "Scenes", notes)
    shown = in_percent(runs_df).drop(columns=["run", "device", "resize", "overrides"])
    print(shown.to_string(index=False))
    print(
        f"\n{len(runs)} runs ({len(runs_df)} rows) -> {args.out}/runs.md, runs.csv, scenes.md, "
        "scenes.csv"
    )


def write_fits(out: Path) -> None:
    """reports/fits.{md,csv} and each fit's held-out renders (`--fits`)."""
    fits = fit_rows([SCENES_ROOT, ROOT / "datasets"])
    if fits.empty:
        print(f"no fitted scenes under {SCENES_ROOT} or datasets/: run `make scenes` first")
        return
    atomic_write_text(out / "fits.csv", fits.to_csv(index=False))
    atomic_write_text(
        out / "fits.md",
        "# Fitted scenes (`make scenes`)\n\n- PSNR in dB on the training views, the held-out "
        "views (every 8th by name) and, where the dataset has object masks, inside them.\n"
        "- recipe: the fit's settings that differ from today's defaults "
        "(`sagonline.fitting.FitConfig`); `predates:` names settings the fit ran without.\n\n"
        + fits.to_markdown(index=False, floatfmt=".4g")
        + "\n",
    )
    for folder in fits["folder"]:
        stack_heldout_renders(ROOT / folder, out)
    print(f"{len(fits)} fitted scenes -> {out}/fits.md, fits.csv")


if __name__ == "__main__":
    main()
