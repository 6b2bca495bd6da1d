"""A segmenter on every N-th view of a real capture: its time against what it scores.

    python -m bench.runners.every [--captures duck_queen] [--segmenter sam2_tiny]
                                  [--every 1,2,4,8] [--out reports]

On a CPU a model's encoder takes seconds a view (SAM 2 Hiera-tiny about 2.5 s on two cores), so
a capture of 200 photographs takes minutes to segment. `dataset.adapter.every=N` (`sagonline
segment --every N`) renders and segments every N-th view only, and the reference view; every
masked view is still scored. For each capture present and fitted and each N, the real-capture
evaluation (`bench.runners.real`'s, the reference view left out of the scores) runs with the
embedding cache off, so each N pays for its own encoder passes: seconds of segmenting, time to
first mask, the segmenter's own mIoU on the views it saw and the vote's on every view.
Each run goes to `multirun/real/<capture>/<segmenter>@dataset.adapter.every-<N>+...`; a rerun
reads the finished ones. Table: <out>/every.md and .csv.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from bench import OUT_HELP, REPORTS
from bench.runners import captures
from bench.runners.real import Evaluations
from bench.tables.report import in_percent, weights_lines, write_table
from sagonline.score.run_metrics import RunMetrics

COLD = ("segmenter.embedding_cache=none",)  # each N pays for its own encoder passes


def setting(every: int) -> tuple[str, ...]:
    return (f"dataset.adapter.every={every}", *COLD)


def row(capture: str, segmenter: str, every: int, m: RunMetrics) -> dict:
    """One run's line: views segmented, seconds, time to first mask, mIoU (segmenter, vote;
    fractions: the table shows them in percent)."""
    scene = m.first_scene()
    timings = scene.get("timings") or m.timings
    frames = (scene.get("vote") or {}).get("num_masks")  # each view segmented votes
    segment_ms = timings.get("segment_ms_per_frame")
    return {
        "capture": capture,
        "segmenter": segmenter,
        "every": every,
        "views segmented": frames,
        "segment s": round(segment_ms * frames / 1000, 1) if segment_ms and frames else None,
        "time to first mask s": round(timings.get("time_to_first_mask_s") or 0.0, 2) or None,
        "segmenter alone mIoU": m.segmenter_miou,
        "mIoU": m.miou,
        "protocol": m.protocol_id,
    }


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(
        prog="python -m bench.runners.every", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--captures", default="duck_queen", help="comma-separated, or all")
    ap.add_argument("--segmenter", default="sam2_tiny", choices=captures.EVERY_MASK_VOTES)
    ap.add_argument("--every", default="1,2,4,8", help="comma-separated N")
    ap.add_argument("--out", type=Path, default=REPORTS, help=OUT_HELP)
    args = ap.parse_args(argv)
    try:
        steps = [int(n) for n in args.every.split(",")]
    except ValueError:
        steps = [0]
    if any(n < 1 for n in steps):
        ap.error(f"--every {args.every}: give whole numbers of 1 or more, comma-separated")
    names = captures.fitted_named(args.captures, ap.error)
    runs, rows, records = Evaluations(), [], []
    for capture in names:
        for every in steps:
            m = runs.run(capture, args.segmenter, 0, setting(every))
            records.append(m)
            if m is not None:
                rows.append(row(capture, args.segmenter, every, m))
    df = pd.DataFrame(rows)
    notes = [
        "every: the segmenter renders and segments views 0, N, 2N, ... and the reference "
        "(`dataset.adapter.every=N`); every masked view but the reference is scored (mIoU, "
        "percent); segmenter alone: its masks' own, on the views it segmented",
        "segment s: the segmenter's time (ms per view x views), embedding cache off; fit seed 0",
        *weights_lines(records),
        "built by `python -m bench.runners.every`; each run:",
        *(
            "`python -m bench.runners.eval "
            + " ".join(captures.command(c, args.segmenter, 0, setting(n)))
            + "`"
            for c in names
            for n in steps
        ),
    ]
    write_table(df, args.out, "every", title="A segmenter on every N-th view", notes=notes)
    print(in_percent(df).to_string(index=False))
    return df


if __name__ == "__main__":
    main()
