"""The student's answers from averages of its weights over other spans, and the span chosen
leave-one-capture-out (`python -m bench.runners.student --spans`)."""

from __future__ import annotations

import pandas as pd

from bench.tables.loo import kept, leave_one_out
from sagonline.score.run_metrics import RunMetrics

RUN_KEYS = ("capture", "source", "vote", "training seed", "coarse mIoU", "steps")


def span_row(stopped: dict, m: RunMetrics) -> dict:
    """One run's line: its student.md line's keys (`stopped`) and the student's mIoU with the
    average over each span scored where it stopped (metrics.json `extra.refine.span_miou`;
    span 0: the trained weights; fractions: the table shows them in percent)."""
    found = m.scene_extra("refine").get("span_miou") or {}
    by_span = sorted(found.items(), key=lambda item: int(item[0]))
    return {
        **{k: stopped[k] for k in RUN_KEYS},
        **{f"span {span} mIoU": miou for span, miou in by_span},
    }


def span_scores(runs: pd.DataFrame) -> dict[str, dict[str, float]]:
    """capture -> span -> the student's mean mIoU (percent) over the capture's runs (its
    training seeds) in `runs`, span_row's lines of one source and vote."""
    columns = [c for c in runs.columns if c.startswith("span ") and c.endswith(" mIoU")]
    return {
        capture: {
            c.split()[1]: round(100 * float(pd.to_numeric(lines[c]).mean()), 4) for c in columns
        }
        for capture, lines in runs.groupby("capture", sort=False)
    }


def span_choice(df: pd.DataFrame, answers_span: int) -> tuple[pd.DataFrame, list[str]]:
    """Per source and vote of span_row's lines (`df`): each capture held out in turn, the span
    of the best mean over the others chosen and reported on it against `answers_span` (the
    runs' `refine.ema_span`), as `bench.tables.loo` chooses the vote; and a line per source
    and vote saying which span the rule keeps."""
    tables, lines = [], []
    baseline = str(answers_span)
    for (source, vote), runs in df.groupby(["source", "vote"], sort=False):
        scores = span_scores(runs)
        rows = leave_one_out(scores, baseline)
        tables.append(pd.DataFrame(rows).assign(source=source, vote=vote))
        keep = kept(rows, baseline, scores)
        lines.append(
            f"{source}, {vote} vote: "
            + (
                f"span {keep} kept (the best mean over every capture, and no held-out capture "
                "lost more than 1 point by its rotation's choice)"
                if keep
                else f"span {baseline} stays (no other span is the best mean over every "
                "capture without a held-out capture losing more than 1 point)"
            )
        )
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    first = ["source", "vote"]
    return table[first + [c for c in table.columns if c not in first]], lines
