"""Score predicted label maps against ground truth, by this harness's rules, strictly.

    python -m bench.tables.score RUN_DIR [--predictions predictions_refined]
    python -m bench.tables.score PRED_DIR GT_DIR [--protocol ID] [--resize RULE] [--ignore LABEL]

Both folders hold `<scene>/<view>.png` single-channel label maps (0 = background), as a run
writes them (`predictions/`, `ground_truth/`; see sagonline/score/predictions.py): so a peer's
predictions can be scored by our protocol, and ours by theirs. Every ground-truth view needs a
prediction. The rules come from GT_DIR/scoring.json (checked against its schema: the protocol
id, the resize rule, the ignored label), flags override them. The rules are strict:
- sizes must match unless a resize rule is given, and aspect ratios must match always;
- `gt_to_pred` never shrinks the ground truth to a smaller prediction;
- a view whose ground truth is all ignored pixels is skipped and reported, never scored;
- given a run folder (or folders inside one), the SHA-256 of both folders is compared with the
  digests its metrics.json recorded, and the result says whether they match.
Prints per-scene and overall mIoU / mAcc (the overall numbers are the mean over scenes, as a
run's are).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from sagonline.core.errors import DatasetError
from sagonline.core.files import read_json_object
from sagonline.score.metrics import RESIZE_RULES, ScoringError, view_metrics
from sagonline.score.predictions import (
    SCORING_FILE,
    folder_sha256,
    label_maps,
    read_label_map,
)

# A prediction may hold at most this many times its ground truth's pixels (a 4x larger side,
# for `gt_to_pred`); a larger file is refused from its header, before it is decoded.
PREDICTION_PIXELS_OVER_TRUTH = 16


@dataclass(frozen=True)
class ScoringRules:
    """scoring.json: how a ground-truth folder is scored."""

    protocol_id: str | None = None
    resize: str | None = None
    ignore_label: int | None = None


def read_rules(gt_dir: Path) -> ScoringRules:
    """GT_DIR/scoring.json checked against its schema (types and allowed values); absent: no
    rules. A problem names the file and the key."""
    path = gt_dir / SCORING_FILE
    if not path.is_file():
        return ScoringRules()
    raw = read_json_object(path, DatasetError)
    unknown = sorted(set(raw) - {"protocol_id", "resize", "ignore_label"})
    if unknown:
        raise DatasetError(
            f"{path}: unknown key {unknown[0]!r} (protocol_id, resize, ignore_label)"
        )
    protocol, resize, ignore = (raw.get(k) for k in ("protocol_id", "resize", "ignore_label"))
    if protocol is not None and not isinstance(protocol, str):
        raise DatasetError(f"{path}: protocol_id must be a string, got {protocol!r}")
    if resize is not None and resize not in RESIZE_RULES:
        raise DatasetError(f"{path}: resize {resize!r} is not one of {sorted(RESIZE_RULES)}")
    if ignore is not None and (isinstance(ignore, bool) or not isinstance(ignore, int)):
        raise DatasetError(
            f"{path}: ignore_label must be an integer (or null), got {ignore!r} "
            f"({type(ignore).__name__})"
        )
    if ignore is not None and not 0 <= ignore <= 65535:
        raise DatasetError(f"{path}: ignore_label {ignore} is not a label id in [0, 65535]")
    return ScoringRules(protocol, resize, ignore)


def score_folders(
    pred_dir: Path, gt_dir: Path, resize: str | None, ignore: int | None
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
            m = view_metrics(pred, gt, resize, ignore)
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


def recorded_metrics(pred_dir: Path, gt_dir: Path) -> tuple[Path, dict] | None:
    """The run folder both folders sit in, and its metrics.json."""
    run = gt_dir.resolve().parent
    if pred_dir.resolve().parent != run or not (run / "metrics.json").is_file():
        return None
    try:
        metrics = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return (run, metrics) if isinstance(metrics, dict) else None


# The numbers a run records for each predictions folder: (mIoU key, mAcc key) in metrics.json.
RECORDED_KEYS = {"predictions": ("miou", "macc"), "predictions_refined": ("refined_miou", None)}
AGREE = 1e-9  # recorded and re-scored numbers come from the same PNGs: equal up to rounding


def compare_recorded(pred_dir: Path, metrics: dict, rescored: dict) -> dict[str, tuple]:
    """What metrics.json recorded for this predictions folder against the re-score: name ->
    (recorded, re-scored, agree) for mIoU and mAcc (a number not recorded is left out)."""
    keys = RECORDED_KEYS.get(pred_dir.resolve().name, ())
    out = {}
    for name, key in zip(("mIoU", "mAcc"), keys, strict=False):
        if key is None or key not in metrics:
            continue
        value = metrics[key]
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
    views = score_folders(pred_dir, gt_dir, rules.resize, rules.ignore_label)
    scenes = views[views["iou"].notna()].groupby("scene")[["iou", "acc"]].mean()
    if scenes.empty:
        return None
    rescored = {"miou": float(scenes["iou"].mean()), "macc": float(scenes["acc"].mean())}
    found = recorded_metrics(pred_dir, gt_dir)
    checks = compare_recorded(pred_dir, found[1], rescored) if found else {}
    return rescored | {"checks": checks}


def parse(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m bench.tables.score", description=__doc__.split("\n")[0]
    )
    ap.add_argument("folders", type=Path, nargs="+", help="RUN_DIR, or PRED_DIR GT_DIR")
    ap.add_argument("--predictions", default="predictions", help="RUN_DIR's folder to score")
    ap.add_argument("--protocol", help="the protocol id to report (default: scoring.json's)")
    ap.add_argument("--resize", choices=sorted(RESIZE_RULES), help="default: scoring.json's")
    ap.add_argument("--ignore", type=int, help="a ground-truth label id to skip, in [0, 65535]")
    args = ap.parse_args(argv)
    if args.ignore is not None and not 0 <= args.ignore <= 65535:
        ap.error(f"--ignore {args.ignore}: a label id in [0, 65535]")
    if len(args.folders) == 1:
        args.pred_dir = args.folders[0] / args.predictions
        args.gt_dir = args.folders[0] / "ground_truth"
    elif len(args.folders) == 2:
        args.pred_dir, args.gt_dir = args.folders
    else:
        ap.error("give RUN_DIR, or PRED_DIR GT_DIR")
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse(argv)
    try:
        for folder in (args.pred_dir, args.gt_dir):
            if not folder.is_dir():
                raise DatasetError(f"{folder}: no such folder")
        if args.pred_dir.resolve() == args.gt_dir.resolve():
            raise DatasetError(
                f"{args.pred_dir}: the predictions folder is the ground truth folder: a score "
                "of 100 would mean nothing"
            )
        rules = read_rules(args.gt_dir)
        resize = args.resize or rules.resize
        ignore = args.ignore if args.ignore is not None else rules.ignore_label
        if args.protocol and rules.protocol_id and args.protocol != rules.protocol_id:
            raise DatasetError(
                f"--protocol {args.protocol}: {args.gt_dir / SCORING_FILE} says this ground truth "
                f"is scored by {rules.protocol_id}; a number is named only by the protocol "
                "that produced it"
            )
        protocol = args.protocol or rules.protocol_id or "(unnamed)"
        views = score_folders(args.pred_dir, args.gt_dir, resize, ignore)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    scored = views[views["iou"].notna()]
    skipped = views[views["iou"].isna()]
    truths = {p.relative_to(args.gt_dir) for p in label_maps(args.gt_dir)}
    unscored = sorted(
        str(p.relative_to(args.pred_dir))
        for p in label_maps(args.pred_dir)
        if p.relative_to(args.pred_dir) not in truths
    )
    if scored.empty:
        print(f"error: {args.gt_dir}: every view's ground truth is ignored", file=sys.stderr)
        raise SystemExit(2)
    scenes = scored.groupby("scene")[["iou", "acc"]].mean().reset_index()
    digests = {
        "predictions": folder_sha256(args.pred_dir),
        "ground_truth": folder_sha256(args.gt_dir),
    }
    result = {
        "protocol_id": protocol,
        "miou": float(np.mean(scenes["iou"])),
        "macc": float(np.mean(scenes["acc"])),
        "views": len(scored),
        "skipped_views": [f"{r.scene}/{r.view}" for r in skipped.itertuples()],
        "unscored_predictions": unscored,
        "sha256": digests,
        "matches_run": None,
    }
    print(
        f"protocol {protocol}  resize rule {resize or 'none (sizes must match)'}  "
        f"ignored label {ignore}"
    )
    print(scenes.assign(iou=100 * scenes["iou"], acc=100 * scenes["acc"]).to_string(index=False))
    print(
        f"\noverall mIoU {100 * result['miou']:.2f}  mAcc {100 * result['macc']:.2f}  "
        f"({len(scored)} views, {len(scenes)} scenes)"
    )
    if len(skipped):
        print(
            f"skipped {len(skipped)} view(s) whose ground truth is all ignored pixels: "
            + ", ".join(result["skipped_views"][:5])
        )
    if unscored:
        more = " ..." if len(unscored) > 5 else ""
        print(
            f"warning: {len(unscored)} prediction(s) have no ground truth and were not "
            f"scored: {', '.join(unscored[:5])}{more}"
        )
    print(f"sha256 predictions {digests['predictions']}")
    print(f"sha256 ground truth {digests['ground_truth']}")
    run = recorded_metrics(args.pred_dir, args.gt_dir)
    if run is not None:
        folder, metrics = run
        recorded = metrics.get("sha256") if isinstance(metrics.get("sha256"), dict) else {}
        pred_key = args.pred_dir.resolve().name
        same = {
            "predictions": recorded.get(pred_key) == digests["predictions"],
            "ground_truth": recorded.get("ground_truth") == digests["ground_truth"],
        }
        result["matches_run"] = all(same.values())
        for what, ok in same.items():
            print(
                f"{what}: {'match' if ok else 'DO NOT MATCH'} the digest {folder}/metrics.json "
                "recorded"
            )
        checks = compare_recorded(args.pred_dir, metrics, result)
        result["matches_recorded"] = all(ok for *_, ok in checks.values()) if checks else None
        for name, (value, again, ok) in checks.items():
            shown = f"{100 * value:.4f}" if isinstance(value, (int, float)) else repr(value)
            print(
                f"recorded {name} {shown}: "
                + (
                    "matches the re-score"
                    if ok
                    else f"CONTRADICTED by the re-score {100 * again:.4f}"
                )
            )
        if checks and not result["matches_recorded"]:
            print(
                f"error: {folder}/metrics.json records numbers its own label maps do not "
                "give: it was edited, or written by other code",
                file=sys.stderr,
            )
            raise SystemExit(3)
    return result


if __name__ == "__main__":
    main()
