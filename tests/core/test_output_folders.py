"""Output folders written whole: built beside their place, swapped in, an earlier output
replaced only with overwrite, and what a user added inside an earlier output kept."""

from __future__ import annotations

import json

import pytest

from sagonline.core.outputs import MANIFEST, OutputError, output_folder


def write(out, overwrite=False, text="new"):
    with output_folder(out, overwrite=overwrite, command="test") as tmp:
        (tmp / "labels.json").write_text(text)
        (tmp / "objects").mkdir()
        (tmp / "objects" / "a.ply").write_text(text)


def test_overwrite_keeps_the_files_a_user_added_and_names_them(tmp_path, capsys):
    out = tmp_path / "seg"
    write(out, text="old")
    (out / "notes.txt").write_text("mine")
    (out / "objects" / "b_edited.ply").write_text("mine too")
    (out / "labels.json.bak").write_text("a copy")
    with pytest.raises(OutputError, match="pass --overwrite"):
        write(out)
    write(out, overwrite=True)
    assert (out / "labels.json").read_text() == "new"
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "objects" / "b_edited.ply").read_text() == "mine too"
    assert (out / "labels.json.bak").read_text() == "a copy"
    said = capsys.readouterr().err
    assert "kept what you added there" in said and "notes.txt" in said
    listed = json.loads((out / MANIFEST).read_text())["files"]
    assert "notes.txt" not in listed and "labels.json" in listed
    write(out, overwrite=True)  # and again: still the user's, still not listed
    assert (out / "notes.txt").read_text() == "mine"


def test_a_user_file_under_a_name_the_new_output_takes_is_kept_beside_it(tmp_path):
    out = tmp_path / "seg"
    with output_folder(out, command="test") as tmp:
        (tmp / "labels.json").write_text("old")
    (out / "figure.png").write_text("mine")
    with output_folder(out, overwrite=True, command="test") as tmp:
        (tmp / "labels.json").write_text("new")
        (tmp / "figure.png").write_text("ours")
    assert (out / "figure.png").read_text() == "ours"
    assert (out / "figure.png.yours").read_text() == "mine"
