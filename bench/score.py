"""Score a folder of predicted label maps against a folder of ground truth, by this harness's rules.

    python -m bench.score PRED_DIR GT_DIR [--protocol ID] [--resize RULE] [--ignore LABEL]

Both folders hold `<scene>/<view>.png` single-channel label maps (0 = background), as a run
writes them (`predictions/`, `ground_truth/`; see sagonline/predictions.py): so a peer's
predictions can be scored by our protocol, and ours by theirs. Every ground-truth view needs a
prediction. The rules default to GT_DIR/scoring.json (a run's protocol id, resize rule and
ignored label); flags override them. Prints per-scene and overall mIoU / mAcc (the overall
numbers are the mean over scenes, as a run's are) and the SHA-256 of both folders, which a run's
metrics.json records.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from sagonline.errors import DatasetError  # noqa: E402
from sagonline.metrics import RESIZE_RULES, view_metrics  # noqa: E402
from sagonline.predictions import folder_sha256, read_label_map, read_scoring_rules  # noqa: E402


def score_folders(pred_dir: Path, gt_dir: Path, resize: str, ignore: int | None) -> pd.DataFrame:
    """One row per ground-truth view: scene, view, iou, acc."""
    truths = sorted(gt_dir.glob("*/*.png"))
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
        m = view_metrics(read_label_map(pred_dir / rel), read_label_map(truth), resize, ignore)
        rows.append({"scene": rel.parent.name, "view": rel.stem, "iou": m["iou"], "acc": m["acc"]})
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("pred_dir", type=Path)
    ap.add_argument("gt_dir", type=Path)
    ap.add_argument("--protocol", help="the protocol id to report (default: GT_DIR/scoring.json)")
    ap.add_argument("--resize", choices=sorted(RESIZE_RULES), help="default: scoring.json's")
    ap.add_argument("--ignore", type=int, help="a ground-truth label to skip")
    args = ap.parse_args(argv)
    try:
        rules = read_scoring_rules(args.gt_dir)
        resize = args.resize or rules.get("resize") or "pred_to_gt"
        ignore = args.ignore if args.ignore is not None else rules.get("ignore_label")
        protocol = args.protocol or rules.get("protocol_id") or "(unnamed)"
        views = score_folders(args.pred_dir, args.gt_dir, resize, ignore)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    scenes = views.groupby("scene")[["iou", "acc"]].mean().reset_index()
    result = {
        "protocol_id": protocol,
        "miou": float(np.mean(scenes["iou"])),
        "macc": float(np.mean(scenes["acc"])),
        "views": len(views),
        "sha256": {
            "predictions": folder_sha256(args.pred_dir),
            "ground_truth": folder_sha256(args.gt_dir),
        },
    }
    print(f"protocol {protocol}  resize rule {resize}  ignored label {ignore}")
    print(scenes.assign(iou=100 * scenes["iou"], acc=100 * scenes["acc"]).to_string(index=False))
    print(
        f"\noverall mIoU {100 * result['miou']:.2f}  mAcc {100 * result['macc']:.2f}  "
        f"({len(views)} views, {len(scenes)} scenes)"
    )
    print(f"sha256 predictions {result['sha256']['predictions']}")
    print(f"sha256 ground truth {result['sha256']['ground_truth']}")
    return result


if __name__ == "__main__":
    main()
