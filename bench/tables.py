"""Build the paper's tables from sweep directories: `python -m bench.tables NAME [SWEEP_DIR]`.

NAME is one of:
- timing: time-to-first-mask, setup (vote + refinement) time, initial and refined ms/frame;
- masks: 3D aggregation time and mIoU against the number of voting masks (+ two PNG plots);
- ablation: the vote settings (eps, delta, min votes, margin) and RGC against the baselines;
- robustness: fused mIoU against segmenter corruption (boundary noise x flicker).
Without SWEEP_DIR the newest folder under multirun/<NAME>/ (or runs/<NAME>/) is used. Each
table lands in reports/<NAME>.md and .csv, headed by the device, torch version and the exact
command-line overrides of every row.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from bench.report import device_text
from bench.rundir import read_run_metrics
from sagonline.utils import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
PAPER_MASK_MS = {1: 111, 3: 114, 6: 140, 12: 162, 25: 224, 50: 384, 100: 571, 206: 1466}


def newest(name: str) -> Path:
    for base in (ROOT / "multirun" / name, ROOT / "runs" / name):
        dirs = sorted(p for p in base.glob("*") if p.is_dir()) if base.exists() else []
        if dirs:
            return dirs[-1]
    raise SystemExit(f"no sweep found under multirun/{name}/: run `make table-{name}` first")


def load_runs(sweep: Path) -> list[dict]:
    runs = []
    for path in sorted(sweep.rglob("metrics.json")):
        m = read_run_metrics(path)
        if m is None or m.get("status") == "failed":
            continue
        # Labels come from what the run recorded beside its numbers, never from .hydra/,
        # which is a separate file.
        if "overrides" not in m:
            m["overrides"] = ["(overrides not recorded: run made before provenance)"]
        m["_dir"] = str(path.parent.relative_to(ROOT) if path.is_relative_to(ROOT) else path.parent)
        runs.append(m)
    if not runs:
        raise SystemExit(f"{sweep}: no finished jobs (metrics.json) yet")
    return runs


def pct(v):
    return None if v is None else round(100 * v, 2)


def timing_rows(runs):
    rows = []
    for m in runs:
        for s in m["scenes"]:
            t = s.get("timings", {})
            rows.append(
                {
                    "scene": s["scene"],
                    "segmenter": m["segmenter"],
                    "time_to_first_mask_s": t.get("time_to_first_mask_s"),
                    "vote_s": t.get("vote_s"),
                    "refine_train_s": t.get("refine_train_s"),
                    "setup_s": (t.get("vote_s") or 0) + (t.get("refine_train_s") or 0),
                    "segmenter_ms_per_frame": t.get("segment_ms_per_frame"),
                    "initial_ms_per_frame": t.get(
                        "initial_ms_per_frame", t.get("label_render_ms_per_frame")
                    ),
                    "refined_ms_per_frame": t.get("refined_ms_per_frame"),
                    "initial_mIoU": pct(s.get("miou")),
                    "refined_mIoU": pct(s.get("refined_miou")),
                    "overrides": " ".join(m.get("overrides", [])),
                }
            )
    return pd.DataFrame(rows)


def masks_rows(runs):
    rows = []
    for m in runs:
        for s in m["scenes"]:
            n = s["vote"]["num_masks"]
            rows.append(
                {
                    "scene": s["scene"],
                    "num_masks": n,
                    "aggregation_ms": 1000 * s["timings"]["vote_s"],
                    "ms_per_mask": s["timings"]["vote_ms_per_mask"],
                    "mIoU": pct(s.get("miou")),
                    "labels3d_acc": pct((s.get("labels3d") or {}).get("accuracy")),
                    "coverage": pct((s.get("labels3d") or {}).get("coverage")),
                    "paper_ms (RTX 4090)": PAPER_MASK_MS.get(n),
                    "overrides": " ".join(m.get("overrides", [])),
                }
            )
    return pd.DataFrame(rows).sort_values(["scene", "num_masks"])


def ablation_rows(runs):
    rows = []
    for m in runs:
        c = m["consensus"]
        rows.append(
            {
                "method": c["method"],
                "eps": c["eps"],
                "delta": c["delta"],
                "min_votes": c["min_votes"],
                "margin": c["margin"],
                "segmenter": m["segmenter"],
                "segmenter_mIoU": pct(m.get("segmenter_miou")),
                "mIoU": pct(m.get("miou")),
                "mAcc": pct(m.get("macc")),
                "labels3d_acc": pct(_mean3d(m, "accuracy")),
                "coverage": pct(_mean3d(m, "coverage")),
                "overrides": " ".join(m.get("overrides", [])),
            }
        )
    return pd.DataFrame(rows).sort_values(["method", "eps", "delta", "min_votes", "margin"])


def robustness_rows(runs):
    rows = []
    for m in runs:
        seg = m["config"]["segmenter"]
        rows.append(
            {
                "boundary_px": seg.get("boundary_px"),
                "flicker": seg.get("flicker"),
                "swap": seg.get("swap"),
                "blob_rate": seg.get("blob_rate"),
                "segmenter_mIoU": pct(m.get("segmenter_miou")),
                "fused_mIoU": pct(m["miou"]),
                "gain": round(100 * (m["miou"] - m["segmenter_miou"]), 2),
                "labels3d_acc": pct(_mean3d(m, "accuracy")),
                "overrides": " ".join(m.get("overrides", [])),
            }
        )
    return pd.DataFrame(rows).sort_values(["boundary_px", "flicker"])


def _mean3d(m, key):
    vals = [s["labels3d"][key] for s in m["scenes"] if s.get("labels3d")]
    return sum(vals) / len(vals) if vals else None


def plot_masks(df: pd.DataFrame, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for col, label, stem in (
        ("mIoU", "mIoU (%) at held-out views", "masks_miou"),
        ("aggregation_ms", "3D aggregation time (ms)", "masks_time"),
    ):
        fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
        for scene, part in df.groupby("scene"):
            ax.plot(part["num_masks"], part[col], "o-", label=scene)
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


def protocol_of(run: dict) -> str:
    """A run's protocol id (runs recorded before ids existed: `<dataset>/unversioned`)."""
    return run.get("protocol_id") or f"{run['dataset']}/unversioned"


def build(name: str, sweep: Path, out: Path) -> pd.DataFrame:
    runs = load_runs(sweep)
    protocols = sorted({protocol_of(m) for m in runs})
    if len(protocols) > 1:  # rows of one table are compared and averaged: one protocol only
        raise SystemExit(
            f"{sweep}: its jobs ran different evaluation protocols ({', '.join(protocols)}); "
            "a table holds one protocol: build one table per sweep of a single protocol"
        )
    df = BUILDERS[name](runs)
    devices = sorted({device_text(m["device"]) for m in runs})
    first = runs[0]
    header = [
        f"# {TITLES[name]}",
        "",
        f"- sweep: `{sweep.relative_to(ROOT) if sweep.is_relative_to(ROOT) else sweep}`"
        f" ({len(runs)} jobs)",
        f"- device: {'; '.join(devices)}",
        f"- dataset: {first['dataset']}, protocol: `{protocols[0]}`, renderer: "
        f"{first['renderer']}, resize rule: {first['resize_rule']}",
        "- mIoU / accuracy in percent; times are wall clock on the device above.",
        "- exact per-row config: the `overrides` column (full config in each job's metrics.json).",
        "",
    ]
    body = df.to_markdown(index=False, floatfmt=".4g")
    out.mkdir(parents=True, exist_ok=True)
    plots = plot_masks(df, out) if name == "masks" else []
    images = "".join(f"\n![{p.stem}]({p.name})\n" for p in plots)
    atomic_write_text(out / f"{name}.csv", df.to_csv(index=False))
    atomic_write_text(out / f"{name}.md", "\n".join(header) + body + "\n" + images)
    return df


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("name", choices=sorted(BUILDERS))
    ap.add_argument("sweep", nargs="?", type=Path)
    ap.add_argument("--out", type=Path, default=ROOT / "reports")
    args = ap.parse_args(argv)
    sweep = args.sweep or newest(args.name)
    df = build(args.name, sweep.resolve(), args.out)
    print(df.drop(columns=["overrides"]).to_string(index=False))
    print(f"\nwrote {args.out}/{args.name}.md and .csv")


if __name__ == "__main__":
    main()
