"""`segment --prompts labels.json`: recorded masks found and checked, another scene said, bad
fields and clicks named."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sagonline.apps.cli import main
from tests.refusals import (
    one_error_line,
    user_scene_files,
)


@pytest.fixture
def masked_segmentation(tmp_path, monkeypatch):
    """A segmentation made from a mask given by a path relative to the folder it was run in."""
    folder, scene, cams, gt = user_scene_files(tmp_path / "scene", 4, 40, 30)
    work = tmp_path / "work"
    work.mkdir()
    cv2.imwrite(str(work / "obj.png"), (gt > 0).astype(np.uint8) * 255)
    monkeypatch.chdir(work)
    argv = [
        "segment",
        str(scene),
        "--cameras",
        str(folder / "transforms.json"),
        "--mask",
        "0:obj.png",
        "--out",
        str(tmp_path / "seg"),
        "--no-record",
    ]
    assert main(argv) == 0
    return tmp_path, scene, folder


def test_a_recorded_mask_is_found_from_labels_json_and_checked(
    masked_segmentation, monkeypatch, capsys
):
    """The mask path is recorded relative to labels.json with its SHA-256: a replay from
    another folder that holds another obj.png uses the recorded file (it used the other one),
    and a changed file is refused."""
    tmp, scene, folder = masked_segmentation
    record = json.loads((tmp / "seg" / "labels.json").read_text())
    obj = record["prompt"]["objects"][0]
    assert obj["mask"] == "../work/obj.png" and len(obj["mask_digest"]) == 32
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    cv2.imwrite(str(elsewhere / "obj.png"), np.zeros((30, 40), np.uint8))
    monkeypatch.chdir(elsewhere)
    assert (
        main(
            [
                "segment",
                str(scene),
                "--prompts",
                str(tmp / "seg" / "labels.json"),
                "--out",
                str(tmp / "again"),
                "--no-record",
            ]
        )
        == 0
    )
    assert np.array_equal(
        np.load(tmp / "again" / "labels.npy"), np.load(tmp / "seg" / "labels.npy")
    )
    capsys.readouterr()
    cv2.imwrite(str(tmp / "work" / "obj.png"), np.zeros((30, 40), np.uint8))  # changed
    assert (
        main(
            [
                "segment",
                str(scene),
                "--prompts",
                str(tmp / "seg" / "labels.json"),
                "--out",
                str(tmp / "third"),
            ]
        )
        == 2
    )
    one_error_line(
        capsys.readouterr().err,
        "labels.json",
        "prompt.objects[0].mask",
        "not the file that was recorded",
    )


def test_a_labels_json_of_another_scene_is_said(masked_segmentation, capsys):
    tmp, scene, folder = masked_segmentation
    other = tmp / "other.ply"
    data = bytearray(scene.read_bytes())
    data[-1] ^= 1  # another scene (one value's last bit)
    other.write_bytes(bytes(data))
    assert (
        main(
            [
                "segment",
                str(other),
                "--prompts",
                str(tmp / "seg" / "labels.json"),
                "--out",
                str(tmp / "on_other"),
                "--no-record",
            ]
        )
        == 0
    )
    assert "was recorded on another scene" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda r: r["vote"].update(eps="0.5"), ["vote.eps must be int or float", "'0.5'"]),
        (lambda r: r.update(orbit="abc"), ["orbit must be int", "'abc'"]),
        (
            lambda r: r["prompt"]["objects"][0].update(clicks=[[1, "x"]]),
            ["prompt.objects[0].clicks[0]"],
        ),
        (lambda r: r["prompt"].update(objects="chair"), ["prompt.objects must be list"]),
        (lambda r: r["prompt"].update(view_name=None), ["prompt.view_name must be str"]),
    ],
)
def test_a_bad_prompts_field_is_named(masked_segmentation, capsys, edit, words):
    """A wrong type in a labels.json crashed (vote.eps "0.5", orbit "abc"); errors about its
    clicks named a --click the user never typed."""
    tmp, scene, _ = masked_segmentation
    record = json.loads((tmp / "seg" / "labels.json").read_text())
    edit(record)
    bad = tmp / "seg" / "bad.json"  # beside labels.json: the recorded mask path holds
    bad.write_text(json.dumps(record))
    assert main(["segment", str(scene), "--prompts", str(bad), "--out", str(tmp / "o")]) == 2
    line = one_error_line(capsys.readouterr().err, "bad.json", *words)
    assert "--click" not in line


def test_a_recorded_click_outside_its_view_is_named_by_its_field(masked_segmentation, capsys):
    tmp, scene, _ = masked_segmentation
    record = json.loads((tmp / "seg" / "labels.json").read_text())
    record["prompt"]["objects"][0]["clicks"] = [[500.0, 10.0]]
    bad = tmp / "seg" / "far.json"
    bad.write_text(json.dumps(record))
    assert main(["segment", str(scene), "--prompts", str(bad), "--out", str(tmp / "o")]) == 2
    one_error_line(capsys.readouterr().err, "far.json: prompt.objects[0].clicks[0]", "outside")
