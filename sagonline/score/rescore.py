"""Predicted label maps scored against ground truth by this harness's rules, strictly: the
rules a ground-truth folder carries (scoring.json), every view scored, and a run's recorded
numbers checked against its own label maps (`sagonline score` says the result)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from sagonline.core.errors import DatasetError
from sagonline.core.files import read_json_object
from sagonline.scene.io.images import NEAREST_SAMPLING
from sagonline.score.metrics import RESIZE_RULES, ScoringError, view_metrics
from sagonline.score.predictions import SCORING_FILE, label_maps, read_label_map
from sagonline.score.run_metrics import METRICS_FILE, MetricsFileError, RunMetrics

# A prediction may hold at most this many times its ground truth's pixels (a 4x larger side,
# for `gt_to_pred`); a larger file is refused from its header, before it is decoded.
PREDICTION_PIXELS_OVER_TRUTH = 16


@dataclass(frozen=True)
class ScoringRules:
    """scoring.json: how a ground-truth folder is scored. `nearest`: which source pixel a
    resize reads ("centre"; "corner" in the files protocol 1's runs wrote, which lack the key)."""

    protocol_id: str | None = None
    resize: str | None = None
    ignore_label: int | None = None
    nearest: str = "centre"


def read_rules(gt_dir: Path) -> ScoringRules:
    """GT_DIR/scoring.json checked against its schema (types and allowed values); absent: no
    rules. A problem names the file and the key."""
    path = gt_dir / SCORING_FILE
    if not path.is_file():
        return ScoringRules()
    raw = read_json_object(path, DatasetError)
    unknown = sorted(set(raw) - {"protocol_id", "resize", "ignore_label", "nearest"})
    if unknown:
        raise DatasetError(
            f"{path}: unknown key {unknown[0]!r} (protocol_id, resize, ignore_label, nearest)"
        )
    protocol, resize, ignore = (raw.get(k) for k in ("protocol_id", "resize", "ignore_label"))
    if protocol is not None and not isinstance(protocol, str):
        raise DatasetError(f"{path}: protocol_id must be a string, got {protocol!r}")
    nearest = raw.get("nearest", implied_nearest(protocol))
    if not isinstance(nearest, str) or nearest not in NEAREST_SAMPLING:
        raise DatasetError(f"{path}: nearest {nearest!r} is not one of {sorted(NEAREST_SAMPLING)}")
    if resize is not None and (not isinstance(resize, str) or resize not in RESIZE_RULES):
        raise DatasetError(f"{path}: resize {resize!r} is not one of {sorted(RESIZE_RULES)}")
    if ignore is not None and (isinstance(ignore, bool) or not isinstance(ignore, int)):
        raise DatasetError(
            f"{path}: ignore_label must be an integer (or null), got {ignore!r} "
            f"({type(ignore).__name__})"
        )
    if ignore is not None and not 0 <= ignore <= 65535:
        raise DatasetError(f"{path}: ignore_label {ignore} is not a label id in [0, 65535]")
    return ScoringRules(protocol, resize, ignore, nearest)


def implied_nearest(protocol: str | None) -> str:
    """Which source pixel a scoring.json without `nearest` was resized by: its protocol
    version's rule. Version 2 reads each target pixel's centre; its first runs were scored so
    before the key was written. Version 1, and an id with no version, read the top-left
    corner."""
    version = (protocol or "").rpartition("@")[2]
    return "centre" if version.isdigit() and int(version) >= 2 else "corner"


def score_folders(
    pred_dir: Path, gt_dir: Path, resize: str | None, ignore: int | None, nearest: str = "centre"
) -> pd.DataFrame:
    """One row per ground-truth view: scene, view, iou, acc (None for a skipped view), and why
    it was skipped."""
    truths = label_maps(gt_dir)
    if not truths:
        raise DatasetError(f"{gt_dir}: no <scene>/<view>.png label maps")
    missing = [
        t.relative_to(gt_dir) for t in truths if not (pred_dir / t.relative_to(gt_dir)).is_file()
    ]
    if missing:
        shown = ", ".join(str(m) for m in missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise DatasetError(f"{pred_dir}: {len(missing)} view(s) have no prediction: {shown}")
    rows = []
    for truth in truths:
        rel = truth.relative_to(gt_dir)
        try:
            gt = read_label_map(truth)
            pred = read_label_map(pred_dir / rel, PREDICTION_PIXELS_OVER_TRUTH * gt.size)
            m = view_metrics(pred, gt, resize, ignore, nearest)
        except ScoringError as exc:
            raise DatasetError(f"{pred_dir / rel}: {exc}") from None
        rows.append(
            {
                "scene": rel.parent.name,
                "view": rel.stem,
                "iou": m["iou"],
                "acc": m["acc"],
                "skipped": m.get("skipped"),
            }
        )
    return pd.DataFrame(rows)


def recorded_metrics(pred_dir: Path, gt_dir: Path) -> tuple[Path, RunMetrics] | None:
    """The run folder both folders sit in, and its record (None where there is none, or it
    is not a run's record)."""
    run = gt_dir.resolve().parent
    if pred_dir.resolve().parent != run or not (run / METRICS_FILE).is_file():
        return None
    try:
        return run, RunMetrics.of_run(run)
    except MetricsFileError:
        return None


# The numbers a run records for each predictions folder: (mIoU key, mAcc key) in metrics.json.
RECORDED_KEYS = {"predictions": ("miou", "macc"), "predictions_refined": ("refined_miou", None)}
AGREE = 1e-9  # recorded and re-scored numbers come from the same PNGs: equal up to rounding


def compare_recorded(pred_dir: Path, metrics: RunMetrics, rescored: dict) -> dict[str, tuple]:
    """What metrics.json recorded for this predictions folder against the re-score: name ->
    (recorded, re-scored, agree) for mIoU and mAcc (a number not recorded is left out)."""
    keys = RECORDED_KEYS.get(pred_dir.resolve().name, ())
    out = {}
    for name, key in zip(("mIoU", "mAcc"), keys, strict=False):
        if key is None or not metrics.recorded(key):
            continue
        value = getattr(metrics, key)
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = ok and abs(float(value) - rescored[name.lower()]) <= AGREE
        out[name] = (value, rescored[name.lower()], ok)
    return out


def rescore_run(run: Path, predictions: str = "predictions") -> dict | None:
    """A run folder's predictions scored again by its ground truth's rules, quietly: {miou,
    macc, checks: compare_recorded(...)}; None where it has no label maps to score."""
    pred_dir, gt_dir = run / predictions, run / "ground_truth"
    if not (pred_dir.is_dir() and gt_dir.is_dir()):
        return None
    rules = read_rules(gt_dir)
    views = score_folders(pred_dir, gt_dir, rules.resize, rules.ignore_label, rules.nearest)
    scenes = views[views["iou"].notna()].groupby("scene")[["iou", "acc"]].mean()
    if scenes.empty:
        return None
    rescored = {"miou": float(scenes["iou"].mean()), "macc": float(scenes["acc"].mean())}
    found = recorded_metrics(pred_dir, gt_dir)
    checks = compare_recorded(pred_dir, found[1], rescored) if found else {}
    return rescored | {"checks": checks}
