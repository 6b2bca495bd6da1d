"""One capture's views by kind (`python -m bench.tables.report --views NAME`): photographed
views against views between photographs, by angle to the nearest photograph, and the plot of
IoU against that angle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sagonline.core.files import atomic_write_image
from sagonline.score.run_metrics import RunMetrics

# per_view.csv's rows of the fused labels rendered ("coarse"; runs before the name was given
# one meaning called them "initial", which is Table II's 2D segmenter on a novel view)
COARSE = ("coarse", "initial")

ANGLE_BINS = [-0.5, 0.5, 10, 20, 30, 180]  # degrees to the nearest photograph
ANGLE_LABELS = ["photographed", "0-10", "10-20", "20-30", ">30"]


def view_rows(runs: dict[Path, RunMetrics]) -> tuple[pd.DataFrame, dict[str, pd.DataFrame]]:
    """Per run (of a capture with photographs for some views): mIoU over the photographed views
    and over the mask-only ones, over the views whose masks did not vote, and by viewing angle
    to the nearest photograph; plus each run's per-view rows keyed by its label."""
    rows, per_view = [], {}
    for run, m in runs.items():
        views = pd.read_csv(run / "per_view.csv")
        views = views[views["mode"].isin(COARSE)]
        if "photo_angle_deg" not in views:
            continue
        label = " ".join([m.segmenter, *m.overrides])
        per_view[label] = views.assign(_overrides=[m.overrides] * len(views))
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


GAIN_PAST = 0.001  # IoU: a view counts as better or worse past 0.1 point


def refined_gain(views: pd.DataFrame) -> dict:
    """The refinement student's gain over the coarse render, view by view, from one run's
    per_view.csv (its `refined` rows against its coarse ones): the views compared, how many gain
    and lose past 0.1 point, and the mean gain in points by angle to the nearest photograph
    with the views in each group. Empty where the run has no refined rows or no angles."""
    key = ["scene", "view"]
    coarse = views[views["mode"].isin(COARSE)].set_index(key)
    refined = views[views["mode"] == "refined"].set_index(key)["iou"]
    if refined.empty or "photo_angle_deg" not in coarse:
        return {}
    both = coarse.join(refined.rename("refined_iou"), how="inner")
    gain = both["refined_iou"] - both["iou"]
    row = {
        "views": len(both),
        "better": int((gain > GAIN_PAST).sum()),
        "worse": int((gain < -GAIN_PAST).sum()),
    }
    by_angle = pd.cut(both["photo_angle_deg"], ANGLE_BINS, labels=ANGLE_LABELS)
    for name, group in gain.groupby(by_angle, observed=False):
        label = f"{name} deg" if name != "photographed" else "at photo"
        row[f"{label}: gain, points"] = round(100 * float(group.mean()), 2) if len(group) else None
        row[f"{label}: views"] = len(group)
    return row


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
