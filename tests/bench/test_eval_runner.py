"""The Hydra runner end to end on tiny scenes: outputs, overwrite guard, resume from cache."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from bench.runners.eval import evaluate
from bench.runners.rundir import RunExists
from tests.fixtures import cfg_with


@pytest.mark.slow
def test_eval_writes_metrics_csv_and_recording(tmp_path, capsys):
    from sagonline.record.recording import viewer_command

    metrics = evaluate(cfg_with(), tmp_path)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    for key in (
        "dataset",
        "segmenter",
        "consensus",
        "scenes",
        "miou",
        "macc",
        "segmenter_miou",
        "timings",
        "resize_rule",
        "device",
    ):
        assert key in saved, key
    assert saved["dataset"] == "synthetic" and saved["segmenter"] == "oracle"
    assert [s["scene"] for s in saved["scenes"]] == ["forward_single", "cluttered_360"]
    for scene in saved["scenes"]:
        assert 0.5 < scene["miou"] <= 1 and 0.5 < scene["macc"] <= 1
        assert scene["labels3d"]["accuracy"] > 0.9
        assert {"render_ms_per_frame", "vote_ms_per_mask", "time_to_first_mask_s"} <= set(
            scene["timings"]
        )
    assert saved["segmenter_miou"] == pytest.approx(1.0)
    assert metrics["miou"] == saved["miou"]
    rows = pd.read_csv(tmp_path / "per_view.csv")
    assert len(rows) == 6 and set(rows.columns) >= {"scene", "view", "iou", "acc"}
    assert (tmp_path / "recording.rrd").stat().st_size > 10_000
    # the summary names the command that opens it, whichever shell reads it
    assert f"(open with: {viewer_command(tmp_path / 'recording.rrd')})" in capsys.readouterr().out


@pytest.mark.slow
def test_skips_same_run_refuses_another_and_resumes_from_cache(tmp_path, capsys):
    cfg = cfg_with("record=false", "dataset=synthetic_ff")
    first = evaluate(cfg, tmp_path)
    saved = (tmp_path / "metrics.json").read_bytes()
    assert evaluate(cfg, tmp_path)["miou"] == first["miou"]  # same config and inputs: skipped
    with pytest.raises(RunExists):  # another config into a finished run: refused
        evaluate(cfg_with("record=false", "dataset=synthetic_ff", "consensus.eps=0.1"), tmp_path)
    assert (tmp_path / "metrics.json").read_bytes() == saved
    caches = sorted((tmp_path / "cache" / "forward_single").glob("*.store"))
    assert [p.name.split("-")[0] for p in caches] == ["frames", "masks", "vote"]
    stamps = {p: p.stat().st_mtime_ns for p in caches}
    # an interrupted run: metrics never written; the next run reuses every cached stage
    (tmp_path / "metrics.json").unlink()
    capsys.readouterr()
    resumed = evaluate(cfg, tmp_path)
    assert resumed["scenes"][0]["stages"] == dict.fromkeys(("frames", "masks", "vote"), "cached")
    # its vote's time is the one the first run took, marked as such
    row = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("forward_single"))
    assert row.split()[7] == f"{first['scenes'][0]['timings']['vote_ms_per_mask']:.1f}*", row
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())
    # a changed vote setting recomputes only the vote
    evaluate(
        cfg_with("record=false", "dataset=synthetic_ff", "consensus.eps=0.1", "overwrite=true"),
        tmp_path,
    )
    votes = list((tmp_path / "cache" / "forward_single").glob("vote-*.store"))
    assert len(votes) == 2
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())


def test_noisy_oracle_is_repaired_by_the_vote(tmp_path):
    m = evaluate(
        cfg_with(
            "record=false",
            "segmenter=oracle_noisy",
            "dataset=synthetic_360",
            "segmenter.flicker=0.3",
        ),
        tmp_path,
    )
    assert m["segmenter_miou"] < 0.95
    assert m["miou"] > m["segmenter_miou"]


def test_an_overwrite_that_fails_or_is_killed_never_loses_the_finished_run(tmp_path, monkeypatch):
    """overwrite=true writes the new run beside the finished one and swaps it in when whole:
    a failure leaves the old run whole and in place; what a killed replacement left (its
    unfinished run, or the old run moved aside mid-swap) is cleaned up or put back by the
    next run into the folder; a file of the user's stays."""
    import json

    import bench.runners.eval as runner
    from bench.runners.eval import evaluate
    from tests.fixtures import cfg_with

    run = tmp_path / "run"
    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    before = json.loads((run / "metrics.json").read_text())
    (run / "notes.txt").write_text("mine")
    pngs = sorted(p.relative_to(run) for p in (run / "predictions").rglob("*.png"))

    def boom(*args, **kwargs):
        raise RuntimeError("killed mid-run")

    with monkeypatch.context() as m:
        m.setattr(runner, "evaluate_scenes", boom)
        with pytest.raises(RuntimeError):
            evaluate(
                cfg_with(
                    "dataset=synthetic_ff", "record=false", "consensus.eps=0.1", "overwrite=true"
                ),
                run,
            )
    assert json.loads((run / "metrics.json").read_text()) == before
    assert sorted(p.relative_to(run) for p in (run / "predictions").rglob("*.png")) == pngs
    assert not list(tmp_path.glob(".run.*"))
    # a kill -9 during the run: its unfinished run stays beside the folder until the next run
    dead = tmp_path / ".run.new-999999"
    (dead / "predictions").mkdir(parents=True)
    # a kill -9 during the swap: the old run aside, the folder without metrics.json
    aside = tmp_path / ".run.replaced-999999"
    aside.mkdir()
    (run / "metrics.json").rename(aside / "metrics.json")
    (run / "predictions").rename(aside / "predictions")
    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)  # the same run: skipped
    assert json.loads((run / "metrics.json").read_text()) == before
    assert sorted(p.relative_to(run) for p in (run / "predictions").rglob("*.png")) == pngs
    assert not list(tmp_path.glob(".run.*")) and (run / "notes.txt").read_text() == "mine"
    evaluate(
        cfg_with("dataset=synthetic_ff", "record=false", "consensus.eps=0.1", "overwrite=true"), run
    )
    assert json.loads((run / "metrics.json").read_text())["consensus"]["eps"] == 0.1
    assert (run / "notes.txt").read_text() == "mine" and not list(tmp_path.glob(".run.*"))


def test_the_disk_line_counts_a_staged_replacements_cache_as_the_run_folders(tmp_path):
    """The summary's disk line: a cache inside the run folder is its own; a shared one is named
    as such; while a replacement is staged beside the run, the run folder's cache counts."""
    from bench.runners.outputs import disk_line

    run, staged, shared = tmp_path / "run", tmp_path / ".run.new-1", tmp_path / "shared"
    for folder, size in ((run / "cache", 3_000_000), (staged, 1_000_000), (shared, 2_000_000)):
        folder.mkdir(parents=True)
        (folder / "f").write_bytes(b"x" * size)
    assert disk_line(run, run / "cache") == "disk: run folder 3.00 MB (its cache 3.0 MB)"
    assert disk_line(staged, run / "cache", run) == "disk: run folder 4.00 MB (its cache 3.0 MB)"
    line = disk_line(run, shared)
    assert line.startswith(f"disk: run folder 3.00 MB, shared stage cache {shared} 2.0 MB")
    assert disk_line(run, None) == "disk: run folder 3.00 MB"
