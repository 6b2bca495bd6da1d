"""Score predicted label maps against ground truth, by this harness's rules, strictly.

    sagonline score RUN_DIR [--predictions predictions_refined]
    sagonline score PRED_DIR GT_DIR [--protocol ID] [--resize RULE] [--nearest centre|corner]
                                    [--ignore LABEL]

Both folders hold `<scene>/<view>.png` single-channel label maps (0 = background), as a run
writes them (`predictions/`, `ground_truth/`; see sagonline/score/predictions.py): so a peer's
predictions can be scored by our protocol, and ours by theirs. Every ground-truth view needs a
prediction. The rules come from GT_DIR/scoring.json (checked against its schema: the protocol
id, the resize rule, which source pixel a resize reads, the ignored label), flags override them;
a scoring.json without `nearest` is re-scored by its protocol id's version (`@1`, or no version:
each target pixel's top-left corner; `@2`: its centre). The rules are strict:
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
import sys
from pathlib import Path

import numpy as np

from sagonline.core.errors import DatasetError
from sagonline.scene.io.images import NEAREST_SAMPLING
from sagonline.score.metrics import RESIZE_RULES
from sagonline.score.predictions import SCORING_FILE, folder_sha256, label_maps
from sagonline.score.rescore import compare_recorded, read_rules, recorded_metrics, score_folders


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    ap = command_parser(sub, "score")
    ap.add_argument("folders", type=Path, nargs="+", help="RUN_DIR, or PRED_DIR GT_DIR")
    ap.add_argument("--predictions", default="predictions", help="RUN_DIR's folder to score")
    ap.add_argument("--protocol", help="the protocol id to report (default: scoring.json's)")
    ap.add_argument("--resize", choices=sorted(RESIZE_RULES), help="default: scoring.json's")
    ap.add_argument(
        "--nearest",
        choices=sorted(NEAREST_SAMPLING),
        help="the source pixel a resize reads: each target pixel's centre (protocol 2) or "
        "top-left corner (protocol 1); default: scoring.json's",
    )
    ap.add_argument("--ignore", type=int, help="a ground-truth label id to skip, in [0, 65535]")
    ap.set_defaults(func=cmd_score)


def cmd_score(args) -> int:
    score(folders_of(args))
    return 0


def folders_of(args) -> argparse.Namespace:
    """The parsed arguments with pred_dir and gt_dir set (a problem: DatasetError)."""
    if args.ignore is not None and not 0 <= args.ignore <= 65535:
        raise DatasetError(f"--ignore {args.ignore}: a label id in [0, 65535]")
    if len(args.folders) == 1:
        args.pred_dir = args.folders[0] / args.predictions
        args.gt_dir = args.folders[0] / "ground_truth"
    elif len(args.folders) == 2:
        args.pred_dir, args.gt_dir = args.folders
    else:
        raise DatasetError("give RUN_DIR, or PRED_DIR GT_DIR")
    return args


def main(argv: list[str]) -> dict:
    """`sagonline score ARGV` in this process, its result returned (exit 2 on a problem with
    the input, 3 where a run's recorded numbers are contradicted)."""
    from sagonline.apps.cli import build_parser

    try:
        return score(folders_of(build_parser(["score"]).parse_args(["score", *argv])))
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def score(args) -> dict:
    """Score args.pred_dir against args.gt_dir, print the result and return it: protocol_id,
    miou, macc, views, skipped_views, unscored_predictions, sha256, matches_run (and
    matches_recorded for a run's own folders)."""
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
    nearest = args.nearest or rules.nearest
    ignore = args.ignore if args.ignore is not None else rules.ignore_label
    if args.protocol and rules.protocol_id and args.protocol != rules.protocol_id:
        raise DatasetError(
            f"--protocol {args.protocol}: {args.gt_dir / SCORING_FILE} says this ground truth "
            f"is scored by {rules.protocol_id}; a number is named only by the protocol "
            "that produced it"
        )
    protocol = args.protocol or rules.protocol_id or "(unnamed)"
    views = score_folders(args.pred_dir, args.gt_dir, resize, ignore, nearest)
    scored = views[views["iou"].notna()]
    skipped = views[views["iou"].isna()]
    truths = {p.relative_to(args.gt_dir) for p in label_maps(args.gt_dir)}
    unscored = sorted(
        str(p.relative_to(args.pred_dir))
        for p in label_maps(args.pred_dir)
        if p.relative_to(args.pred_dir) not in truths
    )
    if scored.empty:
        raise DatasetError(f"{args.gt_dir}: every view's ground truth is ignored")
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
        f"protocol {protocol}  resize rule {resize or 'none (sizes must match)'}"
        f"{f' (nearest: {nearest})' if resize else ''}  "
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
    check_against_run(args, digests, result)
    return result


def check_against_run(args, digests: dict, result: dict) -> None:
    """Where both folders are a run's own: its recorded digests and numbers against these
    (said, and set in `result`: matches_run, matches_recorded); exit 3 where the numbers its
    metrics.json records are not what its label maps give."""
    run = recorded_metrics(args.pred_dir, args.gt_dir)
    if run is not None:
        folder, metrics = run
        recorded = metrics.sha256
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
