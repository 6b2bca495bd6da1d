"""Table building from sweep folders, and same seed -> same accuracy."""

from __future__ import annotations

import pandas as pd

from bench.eval import evaluate
from bench.tables import build
from tests.test_eval_runner import cfg_with


def test_mask_count_table_and_plots(tmp_path):
    sweep = tmp_path / "sweep"
    for i, n in enumerate((1, "null")):
        evaluate(
            cfg_with(
                "record=false",
                "dataset=synthetic_360",
                f"consensus.num_masks={n}",
                f"cache_dir={tmp_path / 'cache'}",
            ),
            sweep / str(i),
        )
    df = build("masks", sweep, tmp_path / "reports")
    assert df["num_masks"].tolist() == [1, 8]
    assert (df["aggregation_ms"] > 0).all() and df["mIoU"].iloc[1] >= df["mIoU"].iloc[0]
    md = (tmp_path / "reports" / "masks.md").read_text()
    assert "device:" in md and "torch" in md and "masks_time.png" in md
    assert (tmp_path / "reports" / "masks_miou.png").stat().st_size > 1000
    assert len(pd.read_csv(tmp_path / "reports" / "masks.csv")) == 2


def test_same_seed_same_accuracy(tmp_path):
    a = evaluate(
        cfg_with("record=false", "segmenter=oracle_noisy", "dataset=synthetic_ff"), tmp_path / "a"
    )
    b = evaluate(
        cfg_with("record=false", "segmenter=oracle_noisy", "dataset=synthetic_ff"), tmp_path / "b"
    )
    assert a["miou"] == b["miou"] and a["segmenter_miou"] == b["segmenter_miou"]
    assert a["scenes"][0]["labels3d"] == b["scenes"][0]["labels3d"]
