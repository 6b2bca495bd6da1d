"""Every real capture's fits of several seeds in one command: the draws the cross-capture table
and the leave-one-capture-out choice read.

    python -m bench.runners.fit_captures [--captures a,b] [--seeds 0,1,2] [--jobs 2] [OVERRIDES ...]
                                                                      (make fits-captures)

Each (capture, seed) runs `python -m bench.runners.scenes dataset=<capture> seed=<k> progress=false
OVERRIDES` (a fit recipe of one's own: `variant=V fit.X=...`; its fits are then scored as the
candidate `dataset.adapter.fit=V` of `make loo-captures`). `--jobs` fits run at once, each on
one thread (a CPU fit gives the same scene on any thread count). bench.runners.scenes skips a
finished fit, so an interrupted batch resumes where it stopped. Each fit's log goes to
runs/fits/<capture>[-<variant>]-seed<k>.log; a table says what each fit did.

`--width avx512` runs torch's CPU kernels at the other vector width (`ATEN_CPU_CAPABILITY`; every
fit is pinned to AVX2 otherwise): the same recipe rounds otherwise there, another draw of it
(two such draws of one capture scored 53 and 67). Those fits go to the variant `avx512` (or
`<variant>-avx512`); `python -m bench.runners.real --fit avx512` scores them as its table's fits.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd

from bench import ROOT
from bench.runners.captures import FIT, captures, fit_of
from bench.runners.job import check_jobs

LOGS = ROOT / "runs" / "fits"


WIDTHS = ("avx2", "avx512")


def variant_of(overrides: list[str]) -> str | None:
    """The fit recipe's name the overrides give (`variant=V`), None for the default recipe."""
    names = [o.split("=", 1)[1] for o in overrides if o.startswith("variant=")]
    return names[-1] if names else None


def at_width(overrides: list[str], width: str) -> list[str]:
    """The overrides of the fits at `width`: at AVX2 (every fit's) as given, at another width
    into the variant `<variant>-<width>` (`<width>` for the default recipe)."""
    if width == "avx2":
        return list(overrides)
    variant = variant_of(overrides)
    rest = [o for o in overrides if not o.startswith("variant=")]
    return [*rest, f"variant={f'{variant}-{width}' if variant else width}"]


def check_width(width: str) -> None:
    """Refuse a vector width this machine's CPU lacks (torch would fall back to a narrower one
    without a word, and the fits would be AVX2's draws under another name)."""
    env = os.environ | {"ATEN_CPU_CAPABILITY": width}
    probe = "import torch; print(torch.backends.cpu.get_cpu_capability())"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env)
    runs = done.stdout.strip()
    if runs.lower() != width:
        raise SystemExit(
            f"error: --width {width}: torch's CPU kernels run at {runs or '?'} on "
            f"this machine, not {width.upper()}"
        )


def fit_command(capture: str, seed: int, overrides: list[str]) -> list[str]:
    """`python -m bench.runners.scenes`'s arguments for one capture's fit of one seed."""
    return [f"dataset={capture}", f"seed={seed}", "progress=false", *overrides]


def log_path(logs: Path, capture: str, seed: int, variant: str | None) -> Path:
    return logs / f"{capture}{f'-{variant}' if variant else ''}-seed{seed}.log"


def fit_one(capture: str, seed: int, overrides: list[str], env: dict[str, str], logs: Path) -> dict:
    """Run one fit (bench.runners.scenes skips a finished one); what it did, from its log and its
    fit_metrics.json."""
    variant = variant_of(overrides)
    log = log_path(logs, capture, seed, variant)
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with log.open("w") as out:
        done = subprocess.run(
            [sys.executable, "-m", "bench.runners.scenes", *fit_command(capture, seed, overrides)],
            cwd=ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
            env=os.environ | env,
        )
    said = log.read_text().strip().splitlines() or ["(no output)"]
    seconds = round(time.perf_counter() - start, 1)
    row = {
        "capture": capture,
        "seed": seed,
        "variant": variant or "-",
        "seconds": seconds,
        "log": str(log),
    }
    if done.returncode != 0:
        return row | {"status": f"failed: {said[-1]}"}
    skipped = any("already fitted" in line for line in said)
    ply = fit_of(capture, seed, (FIT + variant,) if variant else ())
    metrics = ply.with_name("fit_metrics.json") if ply is not None else None
    values = json.loads(metrics.read_text()) if metrics is not None and metrics.is_file() else {}
    return row | {
        "status": "already fitted" if skipped else "fitted",
        "psnr_heldout": values.get("psnr_heldout"),
        "psnr_train": values.get("psnr_train"),
        "gaussians": values.get("gaussians"),
        "fit_seconds": values.get("fit_seconds"),
    }


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(
        prog="python -m bench.runners.fit_captures", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--captures", help="comma-separated (default: every capture in conf/dataset)")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated fit seeds (default 0,1,2)")
    ap.add_argument("--jobs", type=int, default=1, help="fits at once (default 1; each one thread)")
    ap.add_argument(
        "--width",
        choices=WIDTHS,
        default="avx2",
        help="torch's CPU vector width (default avx2, as every fit; avx512: another draw, into "
        "the variant avx512)",
    )
    ap.add_argument("--logs", type=Path, default=LOGS, help="the fits' logs (default runs/fits)")
    ap.add_argument("--dry-run", action="store_true", help="print the fits' commands and stop")
    ap.add_argument(
        "overrides", nargs="*", help="bench.runners.scenes overrides: variant=V fit.X=..."
    )
    args = ap.parse_args(argv)
    try:
        seeds = sorted({int(s) for s in args.seeds.split(",")})
    except ValueError:
        ap.error(f"--seeds {args.seeds!r}: comma-separated integers, say 0,1,2")
    check_jobs(ap, args.jobs)
    known = captures()
    names = args.captures.split(",") if args.captures else known
    unknown = sorted(set(names) - set(known))
    if unknown:
        ap.error(
            f"--captures: no such capture: {', '.join(unknown)}; the captures: {', '.join(known)}"
        )
    for bad in [
        o
        for o in args.overrides
        if o.lstrip("+~").split("=", 1)[0].split(".")[0] in ("dataset", "seed", "hydra")
    ]:
        ap.error(f"{bad}: give captures with --captures and seeds with --seeds")
    todo = [(capture, seed) for capture in names for seed in seeds]
    overrides = at_width(args.overrides, args.width)
    env = {"ATEN_CPU_CAPABILITY": args.width} if args.width != "avx2" else {}
    if args.dry_run:
        for capture, seed in todo:
            prefix = "".join(f"{k}={v} " for k, v in env.items())
            print(
                f"{prefix}python -m bench.runners.scenes "
                + " ".join(fit_command(capture, seed, overrides))
            )
        return pd.DataFrame()
    if env:
        check_width(args.width)
    env |= {"OMP_NUM_THREADS": "1"} if args.jobs > 1 else {}
    print(f"{len(todo)} fits, {args.jobs} at once; logs in {args.logs}/", flush=True)
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda t: fit_one(t[0], t[1], overrides, env, args.logs), todo))
    df = pd.DataFrame(rows)
    print(df.to_string(index=False))
    if df["status"].str.startswith("failed").any():
        raise SystemExit(1)
    return df


if __name__ == "__main__":
    main()
