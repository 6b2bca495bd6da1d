"""`sagonline score`: it cannot be fooled (linked folders, the truth as predictions, all-ignored
views, rules off their schema, digests that lie); metrics are strict JSON."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.fixtures import (
    cfg_with,
)
from tests.refusals import error_line


def _label_folders(tmp_path: Path) -> tuple[Path, Path]:
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    for folder in (gt / "s", pred / "s"):
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / "v.png"), np.eye(8, dtype=np.uint8))
    return pred, gt


def score(*argv: str) -> tuple[int, str, str]:
    import contextlib
    import io

    from sagonline.apps.cli.score import main as score_main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            score_main(list(argv))
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def test_score_digests_what_it_scored_through_a_linked_scene_folder(tmp_path):
    """A scene folder that is a symbolic link was scored but left out of the SHA-256 (the
    digest of empty input beside mIoU 100)."""
    pred, gt = _label_folders(tmp_path)
    real = tmp_path / "elsewhere"
    (pred / "s").rename(real)
    (pred / "s").symlink_to(real, target_is_directory=True)
    code, out, _ = score(str(pred), str(gt))
    assert code == 0
    empty = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
    assert empty not in out and "overall mIoU 100.00" in out


def test_score_refuses_the_ground_truth_as_predictions_and_names_extras(tmp_path):
    pred, gt = _label_folders(tmp_path)
    code, _, err = score(str(gt), str(gt))
    assert code == 2 and "is the ground truth folder" in err
    cv2.imwrite(str(pred / "s" / "extra.png"), np.zeros((8, 8), np.uint8))
    (pred / "t").mkdir()
    cv2.imwrite(str(pred / "t" / "w.png"), np.zeros((8, 8), np.uint8))
    code, out, _ = score(str(pred), str(gt))
    assert code == 0 and "2 prediction(s) have no ground truth" in out and "t/w.png" in out
    code, _, err = score(str(pred), str(gt), "--ignore", "-1")
    assert code == 2 and "--ignore -1: a label id in [0, 65535]" in err


def _label_maps(folder, scene="s", views=None, **files):
    for view, image in (views or files).items():
        path = folder / scene / f"{view}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), image)


def _score(*args):
    from sagonline.apps.cli.score import main as score

    return score([str(a) for a in args])


def test_the_scorer_cannot_be_fooled(tmp_path, capsys):
    gt = np.zeros((40, 60), np.uint8)
    gt[10:30, 20:40] = 1
    _label_maps(tmp_path / "gt", v0=gt)
    _label_maps(tmp_path / "tiny", v0=np.zeros((2, 3), np.uint8))  # the aspect of 40x60
    _label_maps(tmp_path / "wide", v0=np.zeros((40, 90), np.uint8))
    _label_maps(tmp_path / "half", v0=cv2.resize(gt, (30, 20), interpolation=cv2.INTER_NEAREST))
    for pred, flags, message in (
        ("tiny", ["--resize", "gt_to_pred"], "smaller than the ground truth"),
        ("wide", ["--resize", "pred_to_gt"], "other aspect ratios"),
        ("half", [], "give a resize rule"),
    ):
        with pytest.raises(SystemExit) as exc:
            _score(tmp_path / pred, tmp_path / "gt", *flags)
        assert exc.value.code == 2
        error_line(capsys, message)
    assert _score(tmp_path / "half", tmp_path / "gt", "--resize", "pred_to_gt")["miou"] == 1.0


def test_a_view_that_is_all_ignored_is_skipped_not_perfect(tmp_path, capsys):
    gt = np.zeros((20, 20), np.uint8)
    gt[5:15, 5:15] = 1
    void = np.full((20, 20), 255, np.uint8)
    _label_maps(tmp_path / "gt", v0=gt, v1=void)
    _label_maps(tmp_path / "pred", v0=np.zeros_like(gt), v1=np.zeros_like(gt))
    result = _score(tmp_path / "pred", tmp_path / "gt", "--ignore", "255")
    assert result["miou"] == 0.0 and result["views"] == 1
    assert result["skipped_views"] == ["s/v1"]
    assert "skipped 1 view" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("rules", "message"),
    [
        ({"ignore_label": "255"}, "ignore_label must be an integer"),
        ({"ignore_label": True}, "ignore_label must be an integer"),
        ({"resize": "stretch"}, "resize 'stretch' is not one of"),
        ({"protocol_id": 3}, "protocol_id must be a string"),
        ({"ignore": 255}, "unknown key 'ignore'"),
        ({"resize": ["pred_to_gt"]}, "resize ['pred_to_gt'] is not one of"),
        ({"nearest": "middle"}, "nearest 'middle' is not one of"),
        ({"nearest": {"x": 1}}, "nearest {'x': 1} is not one of"),
        ([1, 2], "holds a list, not an object"),
    ],
)
def test_scoring_rules_are_checked_against_their_schema(tmp_path, rules, message, capsys):
    _label_maps(tmp_path / "gt", v0=np.zeros((8, 8), np.uint8))
    _label_maps(tmp_path / "pred", v0=np.zeros((8, 8), np.uint8))
    (tmp_path / "gt" / "scoring.json").write_text(json.dumps(rules))
    with pytest.raises(SystemExit):
        _score(tmp_path / "pred", tmp_path / "gt")
    error_line(capsys, message)


def test_a_protocol_1_run_is_rescored_by_the_resize_it_was_scored_with(tmp_path, capsys):
    """A scoring.json without `nearest` is re-scored by its protocol version's resize: a
    protocol 1 run's prediction is drawn up to the truth reading each target pixel's top-left
    source pixel, as it was scored then; a protocol 2 run's, the centre's (its first runs wrote
    no `nearest`). Today's files say `centre`; --nearest overrides either."""
    from sagonline.score.metrics import view_metrics

    rng = np.random.default_rng(1)
    pred = rng.integers(0, 2, (7, 7)).astype(np.uint8)
    gt = rng.integers(0, 2, (30, 30)).astype(np.uint8)
    _label_maps(tmp_path / "gt", v0=gt)
    _label_maps(tmp_path / "pred", v0=pred)
    corner, centre = (
        view_metrics(pred, gt, "pred_to_gt", nearest=n)["iou"] for n in ("corner", "centre")
    )
    assert corner != centre
    rules = {"protocol_id": "cap/all-views@1", "resize": "pred_to_gt", "ignore_label": None}
    scoring = tmp_path / "gt" / "scoring.json"
    scoring.write_text(json.dumps(rules))
    assert _score(tmp_path / "pred", tmp_path / "gt")["miou"] == corner
    assert "resize rule pred_to_gt (nearest: corner)" in capsys.readouterr().out
    scoring.write_text(json.dumps(rules | {"nearest": "centre"}))
    assert _score(tmp_path / "pred", tmp_path / "gt")["miou"] == centre
    assert _score(tmp_path / "pred", tmp_path / "gt", "--nearest", "corner")["miou"] == corner
    # the first protocol 2 runs wrote no `nearest`: their version says how they were scored
    for protocol, rule in (("cap/all-views@2", centre), ("cap/all-views", corner)):
        scoring.write_text(json.dumps(rules | {"protocol_id": protocol}))
        assert _score(tmp_path / "pred", tmp_path / "gt")["miou"] == rule, protocol


def test_the_scorer_checks_a_runs_digests(tmp_path, capsys):
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    metrics = evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    result = _score(run)
    assert result["matches_run"] is True and abs(result["miou"] - metrics["miou"]) < 1e-12
    assert json.loads((run / "ground_truth" / "scoring.json").read_text())["nearest"] == "centre"
    assert "predictions: match" in capsys.readouterr().out
    some = next((run / "predictions").rglob("*.png"))
    cv2.imwrite(str(some), np.zeros_like(cv2.imread(str(some), cv2.IMREAD_UNCHANGED)))
    with pytest.raises(SystemExit) as exc:  # and the numbers it records no longer hold
        _score(run)
    out = capsys.readouterr().out
    assert exc.value.code == 3 and "predictions: DO NOT MATCH" in out
    assert "CONTRADICTED by the re-score" in out


def test_metrics_are_strict_json():
    from sagonline.core.files import to_json

    text = to_json({"a": float("nan"), "b": [float("inf"), 1.5], "c": np.float32(2)})
    assert json.loads(text) == {"a": None, "b": [None, 1.5], "c": 2.0}
    assert "NaN" not in text and "Infinity" not in text
