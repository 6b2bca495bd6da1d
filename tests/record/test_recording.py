"""The rerun recording read back with rerun's own reader: entities, counts, timelines, layout."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from bench.runners.eval import evaluate
from sagonline.record.recording import ELLIPSOID_LIMIT
from tests.fixtures import cfg_with

TRAJECTORY, EVAL = 8, 3  # the tiny synthetic preset of the runner tests


def read_back(path):
    """entity path -> {"rows": n, "timelines": set, "columns": set, "instances": {column: n}}."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    found = defaultdict(lambda: {"rows": 0, "timelines": set(), "columns": set(), "instances": {}})
    for chunk in reader.stream().to_chunks():
        entry = found[chunk.entity_path]
        entry["rows"] += chunk.num_rows
        entry["timelines"] |= set(chunk.timeline_names) - {"log_time"}
        batch = chunk.to_record_batch()
        entry["columns"] |= set(batch.schema.names)
        for name in batch.schema.names:
            if name.endswith((":centers", ":positions")):
                entry["instances"][name] = sum(len(v) for v in batch.column(name).to_pylist())
    return found, reader.blueprints()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    metrics = evaluate(
        cfg_with(
            "dataset=synthetic_ff",
            "refine=student",
            "refine.max_steps=3",
            "refine.batch_size=2",
        ),
        out,
    )
    return metrics, *read_back(out / "recording.rrd")


@pytest.mark.slow
def test_cameras_frames_and_masks_in_their_frusta(recorded):
    _, found, _ = recorded
    base = "/scenes/forward_single"
    cam = found[f"{base}/trajectory/camera"]
    assert cam["rows"] == TRAJECTORY and cam["timelines"] == {"frame"}
    assert {"Pinhole:image_from_camera", "Pinhole:resolution", "Transform3D:mat3x3"} <= cam[
        "columns"
    ]
    for image in ("rgb", "segmenter"):
        entry = found[f"{base}/trajectory/camera/{image}"]
        assert entry["rows"] == TRAJECTORY and entry["timelines"] == {"frame"}
    for image in ("rgb", "prediction", "ground_truth", "refined"):
        entry = found[f"{base}/eval/camera/{image}"]
        assert entry["rows"] == EVAL and entry["timelines"] == {"eval_view", "frame"}, image
    assert found[f"{base}/eval/camera"]["rows"] == EVAL


def test_per_view_iou_series_match_per_view_rows(recorded):
    metrics, found, _ = recorded
    base = "/scenes/forward_single/metrics"
    assert found[f"{base}/iou"]["rows"] == EVAL
    assert found[f"{base}/refined_iou"]["rows"] == EVAL
    assert metrics["scenes"][0]["refined_miou"] is not None


def test_gaussians_split_by_label_with_confidence(recorded):
    metrics, found, _ = recorded
    base = "/scenes/forward_single/gaussians"
    labelled = found[f"{base}/labelled"]["instances"]["Ellipsoids3D:centers"]
    unlabelled = found[f"{base}/unlabelled"]["instances"]["Points3D:positions"]
    n = labelled + unlabelled  # every Gaussian once (~4000: TINY's num_gaussians)
    assert 3000 < n <= ELLIPSOID_LIMIT
    coverage = metrics["scenes"][0]["labels3d"]["coverage"]
    assert labelled / n == pytest.approx(coverage, abs=1e-6)
    voted = found[f"{base}/confidence"]["instances"]["Points3D:positions"]
    assert labelled <= voted <= n


def test_default_blueprint_is_sent(recorded):
    _, _, blueprints = recorded
    assert len(blueprints) == 1 and blueprints[0].kind == "blueprint"


def test_large_scenes_fall_back_to_points(tmp_path):
    import torch

    from sagonline.record.recording import Recorder
    from tests.fixtures import random_gaussians

    g = random_gaussians(ELLIPSOID_LIMIT + 1, "2dgs", seed=0)
    labels = np.ones(len(g), np.int64)
    rec = Recorder(tmp_path / "r.rrd", scenes=["s"])
    rec.annotate("s", ["background", "object"])
    hist = torch.zeros(len(g), 2).numpy()
    rec.gaussians("s", g, np.where(labels > 0, labels, -1), hist)
    rec.close()
    found, _ = read_back(tmp_path / "r.rrd")
    assert found["/scenes/s/gaussians/labelled"]["instances"]["Points3D:positions"] == len(g)
    assert "/scenes/s/gaussians/confidence" not in found or not found[
        "/scenes/s/gaussians/confidence"
    ]["instances"].get("Points3D:positions")


def test_progress_off_a_terminal_says_a_line_every_so_often():
    """Long work is never silent off a terminal: a line when it starts, one at most every
    `every` seconds with the time left, one at the end."""
    import io
    import time

    from sagonline.core.progress import Progress

    out = io.StringIO()
    bar = Progress("fit", 6, every=0.05, out=out, terminal=False)
    for _ in range(5):
        time.sleep(0.06)
        bar.update(detail="loss 0.1")
    bar.close()
    lines = out.getvalue().splitlines()
    assert lines[0] == "fit: 6 to do" and lines[-1].startswith("fit: 5 of 6 done in")
    middle = lines[1:-1]
    assert middle and all("left" in ln and "loss 0.1" in ln for ln in middle)


def test_the_command_that_opens_a_recording_runs_the_environments_viewer(tmp_path, monkeypatch):
    """A run says how to open its recording: `rerun` where PATH finds the environment's own (a
    shell where it is activated), else that viewer's path, since a shell where it is not found
    no `rerun` (`make eval` said `rerun recording.rrd`: command not found) or another install's,
    of another version than the one that wrote the file. Relative to the working folder where
    the environment lies below it (`.venv/bin/rerun` in the checkout), quoted for the shell."""
    import os
    import sysconfig
    from pathlib import Path

    from sagonline.record.recording import viewer_command

    own = Path(sysconfig.get_path("scripts")) / "rerun"
    if not own.is_file():
        pytest.skip("rerun-sdk's viewer is not installed in this environment")
    recording = tmp_path / "a run" / "recording.rrd"
    quoted = f"'{recording}'"
    other = tmp_path / "bin"
    other.mkdir()
    (other / "rerun").write_text("#!/bin/sh\n")
    (other / "rerun").chmod(0o755)
    monkeypatch.chdir(tmp_path)  # the environment does not lie below it: its absolute path
    for path in (str(other), str(tmp_path / "none"), f"{other}{os.pathsep}{own.parent}"):
        monkeypatch.setenv("PATH", path)
        assert viewer_command(recording) == f"{own.absolute()} {quoted}"
    monkeypatch.setenv("PATH", f"{own.parent}{os.pathsep}{other}")
    assert viewer_command(recording) == f"rerun {quoted}"
    monkeypatch.setenv("PATH", str(other))
    monkeypatch.chdir(own.parents[1])  # the environment's folder, as the checkout holds .venv
    assert viewer_command(recording) == f"{Path(own.parent.name, 'rerun')} {quoted}"
