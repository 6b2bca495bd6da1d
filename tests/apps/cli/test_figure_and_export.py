"""`sagonline figure` and `sagonline export`: untrusted labels.json refused, another scene or size
refused, export beside the run."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sagonline.apps.cli import main
from tests.fixtures import (
    cfg_with,
    tree_digest,
)
from tests.refusals import (
    generic_capture,
    generic_cfg,
    one_error_line,
    user_scene_files,
)


@pytest.fixture
def segment_folder(tmp_path):
    folder, scene, cams, gt = user_scene_files(tmp_path / "scene", 4, 40, 30)
    ys, xs = np.nonzero(gt)
    click = f"0:{xs[len(xs) // 2] + 0.5},{ys[len(xs) // 2] + 0.5}"
    assert (
        main(
            [
                "segment",
                str(scene),
                "--cameras",
                str(folder / "transforms.json"),
                "--click",
                click,
                "--out",
                str(tmp_path / "seg"),
                "--no-record",
            ]
        )
        == 0
    )
    return tmp_path, tmp_path / "seg", scene


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda r: [1, 2], ["holds a list"]),
        (lambda r: {k: v for k, v in r.items() if k != "scene"}, ["scene must name"]),
        (lambda r: {**r, "names": ["background"]}, ["ids must lie in [0, 1)"]),
    ],
)
def test_figure_refuses_a_labels_json_it_cannot_trust(segment_folder, capsys, edit, words):
    tmp, seg, _ = segment_folder
    path = seg / "labels.json"
    path.write_text(json.dumps(edit(json.loads(path.read_text()))))
    assert main(["figure", str(seg), "--out", str(tmp / "f.png")]) == 2
    one_error_line(capsys.readouterr().err, *words)


def test_figure_refuses_another_scene_and_a_label_png_of_another_size(segment_folder, capsys):
    tmp, seg, scene = segment_folder
    record = json.loads((seg / "labels.json").read_text())
    from sagonline.scene.io import read_scene, write_ply

    other = tmp / "other.ply"
    write_ply(other, read_scene(scene).subset(np.arange(100)))
    (seg / "labels.json").write_text(json.dumps({**record, "scene": str(other)}))
    assert main(["figure", str(seg), "--out", str(tmp / "f.png")]) == 2
    one_error_line(capsys.readouterr().err, "not the file the labels were made on")
    (seg / "labels.json").write_text(json.dumps(record))
    png = next((seg / "views").glob("0000_*_labels.png"))
    cv2.imwrite(str(png), np.zeros((1, 1), np.uint8))
    assert main(["figure", str(seg), "--out", str(tmp / "f.png")]) == 2
    one_error_line(capsys.readouterr().err, "1x1, but view 0 renders at 40x30")


def test_export_writes_beside_the_run_not_into_it(tmp_path, monkeypatch):
    """`sagonline export RUN` leaves the finished run's folder as the run wrote it: the default
    output is export-<parent>-<run> in the current folder."""
    from bench.runners.eval import evaluate

    run = tmp_path / "runs" / "r1"
    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    before = tree_digest(run)
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(run)]) == 0
    assert tree_digest(run) == before
    assert (tmp_path / "export-runs-r1" / "forward_single" / "labels.npy").is_file()


@pytest.mark.slow
def test_export_reads_the_runs_relative_paths_from_where_it_was_started(
    tmp_path, monkeypatch, capsys
):
    """A run of a capture named by a relative root, exported from another folder: its paths
    are read from where it was started (metrics.json's `workdir`; for a run without one, its
    cache_root less its cache_dir), the output goes where this command runs."""
    from bench.runners.eval import evaluate

    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    generic_capture(work / "capture")
    elsewhere.mkdir()
    monkeypatch.chdir(work)
    run = work / "runs" / "r1"
    evaluate(generic_cfg(Path("capture"), "record=false", "cache_dir=.cache/stages"), run)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["workdir"] == str(work) and metrics["config"]["dataset"]["root"] == "capture"
    monkeypatch.chdir(elsewhere)
    for inferred in (False, True):
        if inferred:  # a run from before `workdir`
            (run / "metrics.json").write_text(json.dumps({**metrics, "workdir": None}))
        out = f"out{int(inferred)}"
        assert main(["export", str(run), "--out", out]) == 0, capsys.readouterr().err
        said = capsys.readouterr()
        assert f"read from {work}, where it was started" in said.err
        assert (
            f"-> {out}/capture" in said.out
            and (elsewhere / out / "capture" / "labels.npy").is_file()
        )
    (run / "metrics.json").write_text(json.dumps({**metrics, "workdir": str(tmp_path / "gone")}))
    assert main(["export", str(run), "--out", "out2"]) == 2  # not here: read from this folder
    err = capsys.readouterr().err
    assert f"started in {tmp_path / 'gone'}, which is not here" in err and "capture" in err


def test_a_segment_folder_made_with_relative_paths_is_read_from_another_folder(
    tmp_path, monkeypatch, capsys
):
    """labels.json records the scene and its cameras (found beside it) as absolute paths: its
    figure and its replay run from another folder read the same files."""
    from tests.fixtures import own_scene

    own_scene(tmp_path / "work" / "scene", views=4)
    monkeypatch.chdir(tmp_path / "work")
    argv = ["segment", "scene/point_cloud.ply", "--click", "0:24,18", "--no-record"]
    assert main([*argv, "--out", "seg"]) == 0
    info = json.loads((tmp_path / "work" / "seg" / "labels.json").read_text())
    scene = tmp_path / "work" / "scene"
    assert (info["scene"], info["cameras"]) == (
        str(scene / "point_cloud.ply"),
        str(scene / "transforms.json"),
    )
    monkeypatch.chdir(tmp_path)
    assert main(["figure", "work/seg", "--out", "f.png"]) == 0 and (tmp_path / "f.png").is_file()
    replay = ["segment", "work/scene/point_cloud.ply", "--prompts", "work/seg/labels.json"]
    assert main([*replay, "--out", "again", "--no-record"]) == 0
    assert (tmp_path / "again" / "labels.npy").read_bytes() == (
        tmp_path / "work" / "seg" / "labels.npy"
    ).read_bytes()
    # a folder written before paths were absolute: its cameras, where the same file lies beside
    old = tmp_path / "work" / "seg" / "labels.json"
    old.write_text(json.dumps({**info, "cameras": "scene/transforms.json"}))
    stale = {**info, "scene": "scene/point_cloud.ply"}  # and its figure: where to run it
    (tmp_path / "work" / "stale").mkdir()
    (tmp_path / "work" / "stale" / "labels.json").write_text(json.dumps(stale))
    assert main(["figure", "work/stale", "--out", "g.png"]) == 2
    assert "run figure from the folder it was made in" in capsys.readouterr().err
    assert main([*replay, "--out", "old", "--no-record"]) == 0
    assert "its camera file scene/transforms.json is not here; the same file lies" in (
        capsys.readouterr().err
    )
    (scene / "transforms.json").write_text((scene / "transforms.json").read_text() + " ")
    assert main([*replay, "--out", "changed", "--no-record"]) == 2  # not the file it was made on
    assert "pass --cameras naming it" in capsys.readouterr().err


def test_figure_draws_the_scene_on_the_colour_it_was_fitted_on(segment_folder, capsys):
    """With a fit_config.json of white beside the scene (as `make scenes` writes), the scene's
    tile is drawn on white, as `segment` renders its frames; its view name stays legible."""
    tmp, seg, scene = segment_folder
    shown = {}
    for colour in ("black", "white"):
        if colour == "white":
            (scene.parent / "fit_config.json").write_text('{"background": [1.0, 1.0, 1.0]}')
        out = tmp / f"{colour}.png"
        assert main(["figure", str(seg), "--out", str(out)]) == 0, capsys.readouterr().err
        shown[colour] = cv2.imread(str(out)).astype(int)[22:, :40]  # view 0's scene tile
    black, white = shown["black"], shown["white"]
    empty = black.max(-1) == 0  # no scene and no ink of the view's name
    assert empty.mean() > 0.01 and (white[empty] == 255).all()
    ink = black.min(-1) > 200  # the name's white strokes on black: black strokes on white
    assert ink.sum() >= 3 and (white[ink].max(-1) < 128).all()
