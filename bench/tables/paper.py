"""Build the paper's tables from sweep directories: `python -m bench.tables.paper NAME [SWEEP_DIR]`.

NAME is one of:
- timing: time-to-first-mask, setup (vote + refinement) time, and the paper's answer modes
  (coarse label render; initial: render + 2D segmenter; refined: render + student) in ms/frame,
  each alone and while the student trains;
- masks: 3D aggregation time and mIoU against the number of voting masks (+ two PNG plots);
- ablation: the vote settings (eps, delta, min votes, margin) and RGC against the baselines;
- robustness: fused mIoU against segmenter corruption (boundary noise x flicker).
Without SWEEP_DIR the newest folder under multirun/<NAME>/ (or runs/<NAME>/) is used; with
`--tag T` (e.g. mold_cape) the newest under multirun/<NAME>_T/, and the table is
reports/<NAME>_T.md. Each table lands in reports/ as .md and .csv, headed by the device, the load
average at the end of its jobs (what else ran), the protocol id and the exact command-line
overrides of every row. A sweep may hold several segmenters (one sub-folder each): their rows
sit side by side, never averaged.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from bench import OUT_HELP, REPORTS
from bench.runners.rundir import read_run_metrics
from bench.tables.report import device_text, weights_lines
from bench.tables.views import COARSE
from sagonline.core.files import atomic_write_text
from sagonline.score.run_metrics import RunMetrics

ROOT = Path(__file__).resolve().parents[2]
PAPER_MASK_MS = {1: 111, 3: 114, 6: 140, 12: 162, 25: 224, 50: 384, 100: 571, 206: 1466}


def newest(name: str) -> Path:
    """The newest sweep folder of `name` (a table's name, with its tag)."""
    for base in (ROOT / "multirun" / name, ROOT / "runs" / name):
        dirs = sorted(p for p in base.glob("*") if p.is_dir()) if base.exists() else []
        if dirs:
            return dirs[-1]
    raise SystemExit(f"no sweep found under multirun/{name}/: run `make table-{name}` first")


@dataclass
class SweepRun:
    """A finished job of a sweep: its record, its folder and its held-out views' mIoU."""

    m: RunMetrics
    folder: str
    heldout: dict[str, float | None]


def load_runs(sweep: Path) -> list[SweepRun]:
    runs = []
    for path in sorted(sweep.rglob("metrics.json")):
        m = read_run_metrics(path)
        if m is None or m.status == "failed":
            continue
        # Labels come from what the run recorded beside its numbers, never from .hydra/,
        # which is a separate file.
        if not m.recorded("overrides"):
            m.overrides = ["(overrides not recorded: run made before provenance)"]
        folder = path.parent.relative_to(ROOT) if path.is_relative_to(ROOT) else path.parent
        runs.append(SweepRun(m, str(folder), heldout_miou(path.parent / "per_view.csv")))
    if not runs:
        raise SystemExit(f"{sweep}: no finished jobs (metrics.json) yet")
    return runs


def heldout_miou(per_view: Path) -> dict[str, float | None]:
    """Scene -> mean IoU of the scored views whose masks did not vote (initial answers); None
    where every scored view voted. per_view.csv: one row per scene, view and mode."""
    if not per_view.exists():
        return {}
    df = pd.read_csv(per_view)
    if "voted" not in df or "mode" not in df:
        return {}
    held = df[df["mode"].isin(COARSE) & (~df["voted"].astype(bool))]
    out = {scene: None for scene in df["scene"].astype(str).unique()}
    out.update(held.groupby(held["scene"].astype(str))["iou"].mean().to_dict())
    return out


def _heldout_mean(run: SweepRun) -> float | None:
    vals = [v for v in run.heldout.values() if v is not None]
    return sum(vals) / len(vals) if vals else None


def pct(v):
    return None if v is None else round(100 * v, 2)


def timing_rows(runs):
    """Table II: the three answer modes (coarse label render; initial: render + 2D segmenter;
    refined: render + student), each alone and while the student trains."""
    rows = []
    for run in runs:
        m = run.m
        for s in m.scenes:
            t = s.get("timings", {})
            row = {
                "scene": s["scene"],
                "segmenter": m.segmenter,
                "time_to_first_mask_s": t.get("time_to_first_mask_s"),
                "vote_s": t.get("vote_s"),
                "refine_train_s": t.get("refine_train_s"),
                "setup_s": (t.get("vote_s") or 0) + (t.get("refine_train_s") or 0),
                "segmenter_ms_per_frame (trajectory)": t.get("segment_ms_per_frame"),
            }
            row.update(mode_times(t))
            row.update(
                {
                    "coarse_mIoU": pct(s.get("miou")),
                    "initial_mIoU": pct((s.get("extra") or {}).get("initial_mode_miou")),
                    "refined_mIoU": pct(s.get("refined_miou")),
                    "overrides": " ".join(m.overrides),
                }
            )
            rows.append(row)
    return pd.DataFrame(rows)


def mode_times(t: dict) -> dict:
    """ms per frame of each mode, alone and while the student trains. Runs made before the
    modes were split timed only the coarse render while training (then called initial)."""
    if "coarse_ms_per_frame" not in t:
        t = {
            "coarse_ms_per_frame_training": t.get(
                "initial_ms_per_frame", t.get("label_render_ms_per_frame")
            ),
            "refined_ms_per_frame": t.get("refined_ms_per_frame"),
        }
    out = {}
    for mode in ("coarse", "initial", "refined"):
        out[f"{mode}_ms alone"] = t.get(f"{mode}_ms_per_frame")
        out[f"{mode}_ms while training"] = t.get(f"{mode}_ms_per_frame_training")
    return out


def masks_rows(runs):
    rows = []
    for run in runs:
        m = run.m
        for s in m.scenes:
            n = s["vote"]["num_masks"]
            timed_here = "vote_s" in s["timings"]  # else the vote came from the stage cache
            t = s["timings"] if timed_here else s.get("cached_timings", {})
            rows.append(
                {
                    "scene": s["scene"],
                    "segmenter": m.segmenter,
                    "num_masks": n,
                    "aggregation_ms": 1000 * t["vote_s"] if "vote_s" in t else None,
                    "ms_per_mask": t.get("vote_ms_per_mask"),
                    "vote_timed_by": "this job" if timed_here else "an earlier job (cached)",
                    "mIoU": pct(s.get("miou")),
                    "heldout_mIoU": pct(run.heldout.get(str(s["scene"]))),
                    "labels3d_acc": pct((s.get("labels3d") or {}).get("accuracy")),
                    "coverage": pct((s.get("labels3d") or {}).get("coverage")),
                    "paper_ms (RTX 4090)": PAPER_MASK_MS.get(n),
                    "overrides": " ".join(m.overrides),
                }
            )
    return pd.DataFrame(rows).sort_values(["scene", "segmenter", "num_masks"])


def ablation_rows(runs):
    rows = []
    for run in runs:
        m = run.m
        c = m.consensus
        rows.append(
            {
                "method": c["method"],
                "eps": c["eps"],
                "delta": c["delta"],
                "weighting": c.get("weighting", "count"),
                "min_votes": c["min_votes"],
                "margin": c["margin"],
                "segmenter": m.segmenter,
                "segmenter_mIoU": pct(m.segmenter_miou),
                "mIoU": pct(m.miou),
                "heldout_mIoU": pct(_heldout_mean(run)),
                "mAcc": pct(m.macc),
                "labels3d_acc": pct(_mean3d(m, "accuracy")),
                "coverage": pct(_mean3d(m, "coverage")),
                "overrides": " ".join(m.overrides),
            }
        )
    keys = ["segmenter", "method", "eps", "delta", "weighting", "min_votes", "margin"]
    return pd.DataFrame(rows).sort_values(keys)


def robustness_rows(runs):
    rows = []
    for run in runs:
        m = run.m
        seg = corruption_of(m.config)
        rows.append(
            {
                "segmenter": m.segmenter,
                "boundary_px": seg.get("boundary_px"),
                "flicker": seg.get("flicker"),
                "swap": seg.get("swap"),
                "blob_rate": seg.get("blob_rate"),
                "segmenter_mIoU": pct(m.segmenter_miou),
                "fused_mIoU": pct(m.miou),
                "heldout_mIoU": pct(_heldout_mean(run)),
                "gain": round(100 * (m.miou - m.segmenter_miou), 2),
                "labels3d_acc": pct(_mean3d(m, "accuracy")),
                "overrides": " ".join(m.overrides),
            }
        )
    return pd.DataFrame(rows).sort_values(["segmenter", "boundary_px", "flicker"])


def corruption_of(config: dict) -> dict:
    """The corruption a run applied, key by key: `corrupt.*` (any segmenter) where set, else
    the oracle's own setting (`segmenter.boundary_px=...`), else 0."""
    corrupt, segmenter = config.get("corrupt") or {}, config["segmenter"]
    keys = ("boundary_px", "flicker", "swap", "blob_rate", "drop")
    return {k: corrupt.get(k) or segmenter.get(k) or 0 for k in keys}


def _mean3d(m: RunMetrics, key: str):
    vals = [s["labels3d"][key] for s in m.scenes if s.get("labels3d")]
    return sum(vals) / len(vals) if vals else None


def plot_masks(df: pd.DataFrame, out: Path, pattern: str = "masks_{}") -> list[Path]:
    """Two PNGs (mIoU and aggregation time against the mask count): `pattern` with "miou" and
    "time" in the place of {}; none where matplotlib is not installed (a GPU machine may lack
    it), the table being whole without them."""
    try:
        import matplotlib
    except ModuleNotFoundError:
        print("masks table: no plots (matplotlib is not installed here); the table is whole")
        return []

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for col, label, stem in (
        ("mIoU", "mIoU (%) at the scored views", pattern.format("miou")),
        ("aggregation_ms", "3D aggregation time (ms)", pattern.format("time")),
    ):
        fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
        for (scene, segmenter), part in df.groupby(["scene", "segmenter"]):
            ax.plot(part["num_masks"], part[col], "o-", label=f"{scene} ({segmenter})")
        if col == "aggregation_ms":
            ax.plot(
                list(PAPER_MASK_MS),
                list(PAPER_MASK_MS.values()),
                "s--",
                color="grey",
                label="paper (RTX 4090)",
            )
        ax.set_xscale("log")
        if col == "aggregation_ms":
            ax.set_yscale("log")
        ax.set_xlabel("number of masks voting")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out / f"{stem}.png"
        tmp = path.with_name(path.stem + ".tmp.png")
        fig.savefig(tmp)
        plt.close(fig)
        tmp.replace(path)
        paths.append(path)
    return paths


BUILDERS = {
    "timing": timing_rows,
    "masks": masks_rows,
    "ablation": ablation_rows,
    "robustness": robustness_rows,
}
TITLES = {
    "timing": "Time efficiency (paper Table: time-to-first-mask and inference speed)",
    "masks": "3D aggregation time and accuracy against the number of masks",
    "ablation": "Vote ablation: RGC settings and the FlashSplat / weighted-mean baselines",
    "robustness": "Robustness of the vote to segmenter corruption",
}


NOTES = {
    "timing": [
        "- modes (the paper's Table II): coarse = the fused 3D labels rendered at the view; "
        "initial = the view rendered and answered by the 2D segmenter (the nearest other "
        "trajectory frame and its mask prompting a two-frame video); refined = the view "
        "rendered and answered by the student. `alone`: each mode answering the eval views "
        "after the student finished; `while training`: the three answering in turn while it "
        "trained in the same process (refined then waits for the training step in flight).",
        "- coarse_mIoU is the run's mIoU (per_view.csv's `coarse` rows); initial_mIoU scores "
        "the 2D segmenter's answers on the same views.",
    ],
}


def protocol_of(m: RunMetrics) -> str:
    """A run's protocol id (runs recorded before ids existed: `<dataset>/unversioned`)."""
    return m.protocol_id or f"{m.dataset}/unversioned"


def load_text(runs: list[RunMetrics]) -> str:
    """The 1-minute load averages recorded at the end of the jobs, against their threads."""
    loads = [m.device.get("load_average_1m") for m in runs]
    loads = [v for v in loads if v is not None]
    if not loads:
        return "not recorded"
    threads = sorted({m.device.get("torch_threads") for m in runs} - {None})
    return (
        f"{min(loads):.2f}-{max(loads):.2f} (1 min, at the end of each job; the jobs' own "
        f"threads: {', '.join(map(str, threads)) or '?'}; above that, something else ran)"
    )


def renderer_text(runs: list[RunMetrics]) -> str:
    """The renderer asked for, and what each stage ran on (`render.backends.plan_backends`;
    older runs recorded the image renderer alone)."""
    asked = sorted({str(m.renderer) for m in runs})

    def used(m: RunMetrics) -> str:
        plan = m.backends
        if plan:
            return f"images {plan['images']}, vote {plan['vote']}, labels {plan['labels']}"
        return str(m.unknown.get("renderer_resolved", m.renderer))

    resolved = sorted({used(m) for m in runs})
    return ", ".join(asked) + ("" if resolved == asked else f" ({'; '.join(resolved)})")


def build(name: str, sweep: Path, out: Path, tag: str | None = None) -> pd.DataFrame:
    runs = load_runs(sweep)
    records = [run.m for run in runs]
    protocols = sorted({protocol_of(m) for m in records})
    if len(protocols) > 1:  # rows of one table are compared and averaged: one protocol only
        raise SystemExit(
            f"{sweep}: its jobs ran different evaluation protocols ({', '.join(protocols)}); "
            "a table holds one protocol: build one table per sweep of a single protocol"
        )
    df = BUILDERS[name](runs)
    devices = sorted({device_text(m.device) for m in records})
    first = records[0]
    header = [
        f"# {TITLES[name]}",
        "",
        f"- sweep: `{sweep.relative_to(ROOT) if sweep.is_relative_to(ROOT) else sweep}`"
        f" ({len(runs)} jobs)",
        f"- device: {'; '.join(devices)}",
        f"- load average: {load_text(records)}",
        f"- dataset: {first.dataset}, protocol: `{protocols[0]}`, "
        f"renderer: {renderer_text(records)}, resize rule: {first.resize_rule}",
        "- mIoU / accuracy in percent; times are wall clock on the device above.",
        "- exact per-row config: the `overrides` column (full config in each job's metrics.json).",
        *(f"- {line}." for line in weights_lines(records)),
        *NOTES.get(name, []),
        "",
    ]
    body = df.to_markdown(index=False, floatfmt=".4g")
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{name}_{tag}" if tag else name
    pattern = "masks_{}" + (f"_{tag}" if tag else "")
    plots = plot_masks(df, out, pattern) if name == "masks" else []
    images = "".join(f"\n![{p.stem}]({p.name})\n" for p in plots)
    # the CSV names the machine in every row (the markdown says it once, in its header)
    atomic_write_text(out / f"{stem}.csv", df.assign(device="; ".join(devices)).to_csv(index=False))
    atomic_write_text(out / f"{stem}.md", "\n".join(header) + "\n" + body + "\n" + images)
    return df


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        prog="python -m bench.tables.paper", description=__doc__.split("\n")[0]
    )
    ap.add_argument("name", choices=sorted(BUILDERS))
    ap.add_argument("sweep", nargs="?", type=Path)
    ap.add_argument("--out", type=Path, default=REPORTS, help=OUT_HELP)
    ap.add_argument("--tag", help="the sweep's and the table's suffix, e.g. mold_cape")
    args = ap.parse_args(argv)
    stem = f"{args.name}_{args.tag}" if args.tag else args.name
    sweep = args.sweep or newest(stem)
    df = build(args.name, sweep.resolve(), args.out, args.tag)
    print(df.drop(columns=["overrides"]).to_string(index=False))
    print(f"\nwrote {args.out}/{stem}.md and .csv")


if __name__ == "__main__":
    main()
