"""Leave-one-capture-out: each capture held out in turn, the setting of the best mean over the
others chosen and reported on it; a setting kept only where no held-out capture loses more than
1 point by its rotation's choice; and reports/real_captures_loo.md's text."""

from __future__ import annotations

import pandas as pd

BASELINE = "defaults"


def leave_one_out(scores: dict[str, dict[str, float]], baseline: str) -> list[dict]:
    """Leave-one-capture-out choice of a setting. scores: capture -> setting -> mIoU (each
    the mean over the capture's fits). For each capture held out, the setting of the best mean
    over the other captures is chosen and reported on it, against the baseline. A row per
    capture: the setting chosen without it, its score there and the change from the baseline."""
    rows = []
    for held in scores:
        others = [c for c in scores if c != held]
        settings = [s for s in scores[held] if all(s in scores[c] for c in others)]
        if not others or baseline not in settings:
            continue
        chosen, mean = best_on(scores, others, settings, baseline)
        rows.append(
            {
                "capture held out": held,
                "chosen on the others": chosen,
                "their mean with it": round(mean[chosen], 2),
                "their mean with the baseline": round(mean[baseline], 2),
                "held out, baseline": round(scores[held][baseline], 2),
                "held out, chosen": round(scores[held][chosen], 2),
                "change": round(scores[held][chosen] - scores[held][baseline], 2),
            }
        )
    return rows


def best_on(
    scores: dict[str, dict[str, float]], captures: list[str], settings: list[str], baseline: str
) -> tuple[str, dict[str, float]]:
    """The setting of the best mean over `captures` (ties: the baseline), and each setting's
    mean there."""
    mean = {s: sum(scores[c][s] for c in captures) / len(captures) for s in settings}
    return max(settings, key=lambda s: (round(mean[s], 6), s == baseline)), mean


def chosen_on_all(scores: dict[str, dict[str, float]], baseline: str) -> str:
    """The setting of the best mean over every capture: what a capture none of these is would
    be run with."""
    settings = [s for s in scores[next(iter(scores))] if all(s in v for v in scores.values())]
    return best_on(scores, list(scores), settings, baseline)[0]


def kept(rows: list[dict], baseline: str, scores: dict[str, dict[str, float]]) -> str | None:
    """The setting leave-one-out keeps: the one chosen on every capture, unless some rotation's
    held-out capture loses more than 1 point by what was chosen without it (then None: the
    baseline stays). Rotations may choose different settings; each is reported on its own
    held-out capture (`leave_one_out`)."""
    if not rows:
        return None
    chosen = chosen_on_all(scores, baseline)
    if chosen == baseline:
        return None
    return chosen if all(r["change"] >= -1.0 for r in rows) else None


def page(
    names: list[str],
    seeds: list[int],
    settings: list[str],
    kept_lines: list[str],
    tables: list[pd.DataFrame],
    per_capture: list[dict],
) -> tuple[str, pd.DataFrame]:
    """The choice's Markdown page and its table (one row per source and capture held out)."""
    df = pd.concat(tables, ignore_index=True)
    text = [
        "# Real captures: settings chosen leave-one-capture-out",
        "",
        f"- captures {', '.join(names)}; fits of seeds {', '.join(map(str, seeds))} where they "
        "exist; each score the mean over a capture's fits (mIoU %).",
        "- each capture held out in turn: the setting with the best mean over the other "
        "captures is chosen and reported on it (`held out, chosen`: the leave-one-out figure); "
        "the setting of the best mean over all of them is kept unless some held-out capture "
        "lost more than 1 point by its rotation's choice.",
        "- candidates: " + "; ".join(f"`{n}`" for n in settings if n != BASELINE),
        "- built by `python -m bench.runners.real --seeds ... --settings ...`.",
        "",
        *kept_lines,
        "",
        df.to_markdown(index=False),
        "",
        "Each capture under each setting:",
        "",
        pd.DataFrame(per_capture).to_markdown(index=False),
        "",
    ]
    return "\n".join(text), df
