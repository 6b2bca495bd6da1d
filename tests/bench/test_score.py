"""Predictions anyone can re-score: a run's label-map PNGs and digests, `sagonline score`
against a scorer written here, protocol ids in every output, and tables that refuse to mix
protocols."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from bench.runners.eval import evaluate
from bench.tables.paper import build
from sagonline.apps.cli.score import main as score
from sagonline.score.predictions import folder_sha256, read_label_map, write_label_map
from tests.fixtures import cfg_with


def independent_miou(pred: np.ndarray, gt: np.ndarray) -> float:
    """IoU over the foreground labels either map holds; 1 when neither holds one."""
    ious = []
    for label in sorted((set(np.unique(pred)) | set(np.unique(gt))) - {0}):
        p, g = pred == label, gt == label
        ious.append((p & g).sum() / (p | g).sum())
    return float(np.mean(ious)) if ious else 1.0


def test_a_run_writes_its_predictions_and_they_rescore_to_its_numbers(tmp_path, capsys):
    run = tmp_path / "run"
    metrics = evaluate(cfg_with("record=false", "segmenter=oracle_noisy"), run)
    saved = json.loads((run / "metrics.json").read_text())
    assert saved["protocol_id"] == "synthetic/held-out-views@1" == metrics["protocol_id"]
    assert set(saved["sha256"]) == {"predictions", "ground_truth"}
    rows = pd.read_csv(run / "per_view.csv")
    assert (rows["protocol"] == "synthetic/held-out-views@1").all()
    assert "protocol synthetic/held-out-views@1" in capsys.readouterr().out
    result = score([str(run / "predictions"), str(run / "ground_truth")])
    assert result["miou"] == pytest.approx(saved["miou"], abs=1e-12)
    assert result["macc"] == pytest.approx(saved["macc"], abs=1e-12)
    assert result["sha256"] == saved["sha256"]
    assert result["protocol_id"] == saved["protocol_id"]
    # and by a scorer written independently, view by view
    for _, row in rows.iterrows():
        name = f"{row['view']}.png"
        pred = read_label_map(run / "predictions" / row["scene"] / name)
        gt = read_label_map(run / "ground_truth" / row["scene"] / name)
        assert independent_miou(pred, gt) == pytest.approx(row["iou"], abs=1e-12)


def test_score_scores_a_peers_folder_and_names_what_is_missing(tmp_path):
    rng = np.random.default_rng(0)
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    expected = []
    for scene in ("a", "b"):
        ious = []
        for view in ("v0", "v1"):
            gt = rng.integers(0, 3, (12, 16))
            pred = np.where(rng.uniform(size=gt.shape) < 0.8, gt, rng.integers(0, 3, gt.shape))
            write_label_map(gt_dir / scene / f"{view}.png", gt)
            write_label_map(pred_dir / scene / f"{view}.png", pred)
            ious.append(independent_miou(pred, gt))
        expected.append(np.mean(ious))
    result = score([str(pred_dir), str(gt_dir), "--protocol", "peer/test@1"])
    assert result["miou"] == pytest.approx(np.mean(expected), abs=1e-12)
    assert result["protocol_id"] == "peer/test@1"
    assert result["sha256"]["ground_truth"] == folder_sha256(gt_dir)
    (pred_dir / "b" / "v1.png").unlink()
    with pytest.raises(SystemExit):
        score([str(pred_dir), str(gt_dir)])


@pytest.mark.slow
def test_a_table_refuses_to_mix_protocols(tmp_path):
    sweep = tmp_path / "sweep"
    cache = f"cache_dir={tmp_path / 'cache'}"
    evaluate(cfg_with("record=false", "dataset=synthetic_ff", cache), sweep / "0")
    evaluate(cfg_with("record=false", "dataset=synthetic_ff", cache, "seed=1"), sweep / "1")
    build("ablation", sweep, tmp_path / "reports")  # one protocol: fine
    assert (
        "protocol: `synthetic/held-out-views@1`" in (tmp_path / "reports/ablation.md").read_text()
    )
    path = sweep / "1" / "metrics.json"
    m = json.loads(path.read_text())
    m["protocol_id"] = "synthetic/other@1"
    path.write_text(json.dumps(m))
    with pytest.raises(SystemExit, match="different evaluation protocols"):
        build("ablation", sweep, tmp_path / "reports2")


def test_a_recorded_number_the_rescore_contradicts_is_never_shown_as_fine(tmp_path, capsys):
    """metrics.json's mIoU edited, the label maps untouched: `sagonline score RUN` names the
    contradiction and exits 3; `bench.tables.report` marks the row CONTRADICTED; a `|` or a line
    break in a recorded field does not break the report's Markdown."""
    from bench.tables.report import main as report

    run = tmp_path / "runs" / "run"
    evaluate(cfg_with("record=false", "segmenter=oracle_noisy"), run)
    assert score([str(run)])["matches_recorded"] is True
    assert "recorded mIoU" in capsys.readouterr().out
    saved = json.loads((run / "metrics.json").read_text())
    saved["miou"] = 0.9999
    saved["segmenter"] = "oracle|noisy\nsecond line"
    (run / "metrics.json").write_text(json.dumps(saved))
    with pytest.raises(SystemExit) as exc:
        score([str(run)])
    out = capsys.readouterr()
    assert exc.value.code == 3 and "CONTRADICTED by the re-score" in out.out
    report([str(tmp_path / "runs"), "--out", str(tmp_path / "reports")])
    table = (tmp_path / "reports" / "runs.md").read_text()
    assert "CONTRADICTED" in table and "oracle\\|noisy second line" in table
    rows = [line for line in table.splitlines() if line.startswith("|")]
    assert len({line.count("|") - line.count("\\|") for line in rows}) == 1


def test_a_protocol_id_is_never_put_over_another_protocols_numbers(tmp_path):
    run = tmp_path / "run"
    evaluate(cfg_with("record=false", "segmenter=oracle"), run)
    with pytest.raises(SystemExit) as exc:
        score([str(run), "--protocol", "nvos/scribbles-skeleton@1"])
    assert exc.value.code == 2


def test_report_out_that_is_a_file_is_one_line(tmp_path, capsys):
    from bench.tables.report import main as report

    target = tmp_path / "file"
    target.write_text("x")
    with pytest.raises(SystemExit) as exc:
        report(["--out", str(target)])
    assert exc.value.code == 2 and "a file, not a folder" in capsys.readouterr().err
