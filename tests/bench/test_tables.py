"""Table building from sweep folders, and same seed -> same accuracy."""

from __future__ import annotations

import pandas as pd
import pytest

from bench.runners.eval import evaluate
from bench.tables.paper import build
from tests.fixtures import cfg_with


@pytest.mark.slow
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
    df = build("masks", sweep, tmp_path / "reports", tag="syn")
    assert df["num_masks"].tolist() == [1, 8]
    assert (df["aggregation_ms"] > 0).all() and df["mIoU"].iloc[1] >= df["mIoU"].iloc[0]
    # synthetic eval views are never trajectory frames: every scored view is held out
    assert df["heldout_mIoU"].tolist() == df["mIoU"].tolist()
    md = (tmp_path / "reports" / "masks_syn.md").read_text()
    assert "device:" in md and "torch" in md and "masks_time_syn.png" in md
    assert "load average: " in md and "not recorded" not in md
    assert (tmp_path / "reports" / "masks_miou_syn.png").stat().st_size > 1000
    assert len(pd.read_csv(tmp_path / "reports" / "masks_syn.csv")) == 2
    assert "weights" not in md  # the oracle reads none
    import json  # a job that recorded its model's files: the page names them

    record = json.loads((sweep / "0" / "metrics.json").read_text())
    record["segmenter_info"] = {"encoder": "/w/e.onnx", "encoder_sha256": "18348d144bd3" * 5}
    (sweep / "0" / "metrics.json").write_text(json.dumps(record))
    build("masks", sweep, tmp_path / "reports", tag="syn")
    md = (tmp_path / "reports" / "masks_syn.md").read_text()
    assert "- oracle's weights (file, sha256): e.onnx 18348d144bd3.\n" in md


@pytest.mark.slow
def test_corrupt_degrades_any_segmenter_as_the_oracle_does(tmp_path):
    """`corrupt.*` on the clean oracle gives the masks the oracle's own corruption gives, and
    the robustness table reads the corruption from either place."""
    sweep, common = tmp_path / "sweep", ["record=false", "dataset=synthetic_ff"]
    own = evaluate(
        cfg_with(*common, "segmenter.flicker=0.3", "segmenter.boundary_px=2"), sweep / "0"
    )
    wrapped = evaluate(
        cfg_with(*common, "corrupt.flicker=0.3", "corrupt.boundary_px=2"), sweep / "1"
    )
    clean = evaluate(cfg_with(*common), tmp_path / "clean")
    assert own["segmenter_miou"] == wrapped["segmenter_miou"] < clean["segmenter_miou"]
    assert own["miou"] == wrapped["miou"]
    df = build("robustness", sweep, tmp_path / "reports")
    assert df["flicker"].tolist() == [0.3, 0.3] and df["boundary_px"].tolist() == [2, 2]


def test_timing_rows_name_the_modes_of_old_and_new_runs():
    from bench.tables.paper import mode_times

    new = {
        f"{m}_ms_per_frame{s}": 1.0
        for m in ("coarse", "initial", "refined")
        for s in ("", "_training")
    }
    assert all(v == 1.0 for v in mode_times(new).values())
    old = mode_times({"initial_ms_per_frame": 45.0, "refined_ms_per_frame": 250.0})
    assert old["coarse_ms while training"] == 45.0 and old["refined_ms alone"] == 250.0
    assert old["initial_ms alone"] is None and old["coarse_ms alone"] is None


@pytest.mark.slow
def test_same_seed_same_accuracy(tmp_path):
    a = evaluate(
        cfg_with("record=false", "segmenter=oracle_noisy", "dataset=synthetic_ff"), tmp_path / "a"
    )
    b = evaluate(
        cfg_with("record=false", "segmenter=oracle_noisy", "dataset=synthetic_ff"), tmp_path / "b"
    )
    assert a["miou"] == b["miou"] and a["segmenter_miou"] == b["segmenter_miou"]
    assert a["scenes"][0]["labels3d"] == b["scenes"][0]["labels3d"]


def test_views_report_splits_photographed_and_mask_only(tmp_path):
    import json

    from PIL import Image

    from bench.tables.report import main

    run = tmp_path / "run"
    run.mkdir()
    metrics = {
        "dataset": "cap",
        "scenes": [],
        "miou": 0.7,
        "segmenter": "oracle",
        "overrides": ["a=1"],
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    pd.DataFrame(
        {
            "scene": "s",
            "view": ["p0", "p1", "m0", "m1", "m2"],
            "mode": "coarse",
            "iou": [0.9, 0.8, 0.7, 0.6, 0.5],
            "acc": 0.9,
            "voted": [True, False, False, False, True],
            "photographed": [True, True, False, False, False],
            "photo_angle_deg": [0.0, 0.0, 5.0, 15.0, 40.0],
            "photo_distance": [0.0, 0.0, 0.1, 0.2, 0.3],
        }
    ).to_csv(run / "per_view.csv", index=False)
    main([str(run), "--views", "cap", "--out", str(tmp_path / "reports")])
    table = pd.read_csv(tmp_path / "reports" / "cap.csv")
    row = table.iloc[0]
    assert row["run"] == "oracle a=1" and row["views"] == 5
    assert row["photographed_mIoU"] == 85.0 and row["mask_only_views"] == 3  # percent
    assert row["not_voted_mIoU"] == 70.0  # p1, m0, m1
    assert row["0-10 deg views"] == 1 and row[">30 deg mIoU"] == 50.0
    assert Image.open(tmp_path / "reports" / "cap_iou_vs_angle.png").size[0] > 400


def test_report_writes_runs_and_scenes_only_merges_identical_runs_in_percent(tmp_path):
    """`make report`: reports/runs.* and scenes.* and nothing else (the fits table and other
    tracked reports are left alone); a copied run is one row counting two; scores in percent."""
    import json
    import shutil

    from bench.tables.report import main

    runs = tmp_path / "runs"
    first = runs / "a"
    first.mkdir(parents=True)
    metrics = {
        "dataset": "d",
        "scenes": [
            {
                "scene": "s",
                "status": "ok",
                "miou": 0.8125,
                "macc": 0.9,
                "timings": {"vote_ms_per_mask": 3.0},
            }
        ],
        "miou": 0.8125,
        "macc": 0.9,
        "segmenter": "oracle",
        "overrides": ["dataset=d"],
        "timings": {"vote_ms_per_mask": 3.0},
    }
    (first / "metrics.json").write_text(json.dumps(metrics))
    shutil.copytree(first, runs / "b")
    metrics["timings"] = {}  # the same run scored again, without timings
    metrics["scenes"][0]["timings"] = {}
    (runs / "c").mkdir()
    (runs / "c" / "metrics.json").write_text(json.dumps(metrics))
    other = dict(metrics, miou=0.5, overrides=["dataset=d", "consensus.eps=0.1"])
    other["scenes"] = [dict(metrics["scenes"][0], cached_timings={"vote_ms_per_mask": 2.5})]
    (runs / "d").mkdir()
    (runs / "d" / "metrics.json").write_text(json.dumps(other))
    out = tmp_path / "reports"
    out.mkdir()
    (out / "fits.md").write_text("kept\n")
    main([str(runs), "--out", str(out)])
    assert sorted(p.name for p in out.iterdir()) == [
        "fits.md",
        "runs.csv",
        "runs.md",
        "scenes.csv",
        "scenes.md",
    ]
    assert (out / "fits.md").read_text() == "kept\n"
    table = pd.read_csv(out / "runs.csv")
    assert sorted(table["runs"]) == [1, 3] and len(table) == 2
    merged = table[table["runs"] == 3].iloc[0]
    assert merged["mIoU"] == 81.25 and merged["vote_ms_per_mask"] == 3.0
    assert merged["run"].endswith("(+2 identical)")
    served = table[table["runs"] == 1].iloc[0]  # its vote from the stage cache: the makers' time
    assert pd.isna(served["vote_ms_per_mask"]) and served["cached_vote_ms_per_mask"] == 2.5
    scenes = pd.read_csv(out / "scenes.csv")
    assert sorted(scenes["runs"]) == [1, 3] and set(scenes["mIoU"]) == {81.25}
    md = (out / "runs.md").read_text()
    assert " 81.25 " in md and "0.8125" not in md and "nan" not in md


def test_plot_legend_names_only_what_differs():
    from bench.tables.views import short_labels

    shared = ["dataset=m", "dataset.adapter.exclude_reference=true"]
    names = short_labels(
        {
            "oracle a b=1": [*shared, "consensus.stride=4"],
            "oracle a b=2": [*shared, "consensus.stride=8"],
            "classical a": [*shared, "record=false"],
        }
    )
    assert names == {
        "oracle a b=1": "oracle stride=4",
        "oracle a b=2": "oracle stride=8",
        "classical a": "classical",
    }


def test_progress_is_silenced_only_when_asked(monkeypatch):
    """Off a terminal (a log file, CI) the runs say plain progress lines, not bars (tested in
    tests/record/test_recording.py); only progress=false silences them."""
    import io
    import types

    from bench.runners.job import quiet

    monkeypatch.setenv("CI", "true")
    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert not quiet(types.SimpleNamespace(progress=True))
    assert quiet(types.SimpleNamespace(progress=False))


def test_the_weights_lines_name_each_models_files_and_say_where_runs_differ():
    """A table's note names the files a model-backed source's runs read, by the digests in
    metrics.json; runs that read other files, or recorded none, are counted, never hidden."""
    from bench.tables.report import weights_lines
    from sagonline.score.run_metrics import RunMetrics

    def run(source: str, encoder: str | None, weights=None) -> RunMetrics:
        info = {"format": "sam2"}
        if encoder:
            info |= {
                "encoder": "/w/sam2_tiny/encoder.ort",
                "encoder_sha256": encoder,
                "decoder": "/w/sam2_tiny/decoder.onnx",
                "decoder_sha256": "4a4c8a8a53d9" + "0" * 52,
            }
        return RunMetrics(
            dataset="cap", segmenter=source, segmenter_info=info, segmenter_weights=weights
        )

    same = [run("sam2_tiny", "54e9ee80bd43" + "1" * 52) for _ in range(2)]
    assert weights_lines([*same, None, run("classical", None)]) == [
        "sam2_tiny's weights (file, sha256): decoder.onnx 4a4c8a8a53d9, encoder.ort 54e9ee80bd43"
    ]
    other = run("sam2_tiny", "ffff00000000" + "2" * 52)
    unrecorded = run("sam2_tiny", None, weights={"/w/sam2_tiny/encoder.ort": "337c"})
    (line,) = weights_lines([*same, other, unrecorded])
    assert line.startswith("sam2_tiny's weights DIFFER between runs (file, sha256): ")
    assert (
        "encoder.ort 54e9ee80bd43 (2 runs)" in line and "encoder.ort ffff00000000 (1 run)" in line
    )
    assert line.endswith("; no digest recorded (1 run)")
    (line,) = weights_lines([*same, unrecorded])  # one set of files, one run without digests
    assert "DIFFER" not in line and "encoder.ort 54e9ee80bd43 (2 runs); no digest" in line
