"""The first GPU fit's row: what `scripts/gpu_check.sh` fitted (fit_metrics.json) and how the
capture scores on it (the real masks' and the classical segmenter's metrics.json), beside the
CPU fit of the same capture and seed (its fit_config.json and fit_metrics.json, which `make
gpu-bundle` carries), as CSV rows and their Markdown table.

    python -m bench.tables.gpu_fit FIT_DIR --runs real=RUN classical=RUN [--cpu-fit DIR]
                                   [--also LABEL=FIT_DIR ...] --out F.csv
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from sagonline.core.files import atomic_write_text

FIT_COLUMNS = (
    "iterations",
    "fit_seconds",
    "gaussians",
    "psnr_train",
    "psnr_heldout",
    "psnr_heldout_object",
)


def fit_row(fit_dir: Path, runs: dict[str, Path], fit: str = "gpu") -> dict:
    """One row: the fit's recipe size and figures (seconds per 1,000 iterations too), and each
    run's mIoU (percent)."""
    metrics = json.loads((fit_dir / "fit_metrics.json").read_text())
    config = json.loads((fit_dir / "fit_config.json").read_text())
    row = {
        "fit": fit,
        "scene": metrics.get("scene"),
        "device": config.get("device"),
        "resolution": "x".join(str(v) for v in metrics.get("resolution", [])),
        "seed": config.get("seed"),
        "init": metrics.get("init"),
    }
    row |= {k: round(v, 2) if isinstance(v := metrics.get(k), float) else v for k in FIT_COLUMNS}
    if metrics.get("iterations") and metrics.get("fit_seconds") is not None:
        row["s per 1k iterations"] = round(1000 * metrics["fit_seconds"] / metrics["iterations"], 1)
    row["stopped"] = metrics.get("stopped")
    for source, run in runs.items():
        run_metrics = json.loads((run / "metrics.json").read_text())
        row[f"{source} mIoU"] = round(100 * run_metrics["miou"], 2)
        row["gpu"] = (run_metrics.get("device") or {}).get("gpu", row.get("gpu"))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fit_dir", type=Path, help="the fit's folder (fit_metrics.json)")
    ap.add_argument("--runs", nargs="*", default=[], help="SOURCE=RUN_DIR, each an evaluation")
    ap.add_argument(
        "--cpu-fit", type=Path, help="the CPU fit's figures (fit_config.json, fit_metrics.json)"
    )
    ap.add_argument(
        "--also",
        nargs="*",
        default=[],
        help="LABEL=FIT_DIR: another fit's figures as a row (split at the last =)",
    )
    ap.add_argument("--out", type=Path, required=True, help="the CSV to write (a .md beside it)")
    args = ap.parse_args()
    runs = {}
    for item in args.runs:
        source, _, folder = item.partition("=")
        if not folder:
            ap.error(f"--runs {item!r}: give SOURCE=RUN_DIR")
        runs[source] = Path(folder)
    rows = [fit_row(args.fit_dir, runs)]
    if args.cpu_fit is not None:
        rows.append(fit_row(args.cpu_fit, {}, fit="cpu (the same capture and seed)"))
    for item in args.also:
        label, _, folder = item.rpartition("=")  # the label may hold "=" (fit=paper)
        if not label or not folder:
            ap.error(f"--also {item!r}: give LABEL=FIT_DIR")
        rows.append(fit_row(Path(folder), {}, fit=label))
    table = pd.DataFrame(rows)
    atomic_write_text(args.out, table.to_csv(index=False))
    atomic_write_text(args.out.with_suffix(".md"), table.to_markdown(index=False) + "\n")
    print(table.to_markdown(index=False))


if __name__ == "__main__":
    main()
