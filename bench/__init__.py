"""The harness around the library, in three kinds: `runners/` make runs (eval, scenes, fits, the
cross-capture table), `tables/` read them back (the paper's tables, reports, re-scoring) and
`speed/` holds the speed benchmarks. Every module runs as `python -m bench.<kind>.<name>` from
the checkout's root."""

from pathlib import Path

import sagonline  # noqa: F401, E402 (sets the OpenMP wait policy and OpenBLAS threads before they load)

ROOT = Path(__file__).resolve().parents[1]
# Where tables, reports and benchmark CSVs go by default: a user's own place, untracked (runs/ is
# ignored). The tables committed in reports/ are rebuilt only when asked for by name:
# `--out reports` (make ... REPORTS=reports).
REPORTS = ROOT / "runs" / "reports"
OUT_HELP = (
    f"where to write (default {REPORTS.relative_to(ROOT)}/, untracked; the committed tables: "
    "--out reports)"
)


def print_and_write(table, out: str | None) -> None:
    """Print a benchmark's table (a pandas DataFrame) and, where `out` names a CSV, write it
    there (atomically) and say so."""
    from sagonline.core.files import atomic_write_text

    print(table.to_string(index=False))
    if out:
        atomic_write_text(out, table.to_csv(index=False))
        print(f"wrote {out}")
