"""`sagonline render`: it never writes over its inputs, checks sizes and backgrounds, and says when
a view shows nothing."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from sagonline.apps.cli import main
from sagonline.scene.io import write_ply
from sagonline.scene.io.cameras import write_3dgs_cameras_json
from tests.fixtures import (
    ROOT,
    llff_scene,
)
from tests.refusals import NAMES, user_scene_files


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "sagonline", *args], cwd=ROOT, capture_output=True, text=True
    )


@pytest.fixture
def scene_files(tmp_path, tiny_task):
    ply = write_ply(tmp_path / "scene.ply", tiny_task.gaussians)
    cams = write_3dgs_cameras_json(tmp_path / "cameras.json", tiny_task.trajectory[:2])
    return ply, cams


@pytest.mark.slow
def test_render_never_writes_over_the_camera_file_of_a_folder(tmp_path, scene_files):
    ply, _ = scene_files
    cams, _ = llff_scene(tmp_path / "llff", NAMES, with_scene=False)
    target = tmp_path / "llff" / "poses_bounds.npy"
    before = target.read_bytes()
    r = _cli(
        "render", str(ply), "--cameras", str(target.parent), "--out", str(target), "--overwrite"
    )
    assert r.returncode != 0 and "one of the inputs" in r.stderr, r.stderr
    assert target.read_bytes() == before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--width", "0", "--height", "108"], "not positive"),
        (["--width", "-192", "--height", "-108"], "not positive"),
        (["--width", "100000", "--height", "100000"], "exceeds the ceiling"),
        (["--background", "a,b"], "three values"),
        (["--background", "1,1"], "three values"),
        (["--background", "2,0,0"], "three values"),
    ],
)
def test_render_sizes_and_backgrounds_are_checked(tmp_path, scene_files, args, message, capsys):
    """In this process (the command line's own entry is run by the other tests here)."""
    ply, cams = scene_files
    code = main(
        ["render", str(ply), "--cameras", str(cams), "--out", str(tmp_path / "v.png"), *args]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert message in err and not (tmp_path / "v.png").exists()


def test_a_view_that_shows_nothing_and_an_extreme_opacity(tmp_path, capsys):
    import warnings

    from plyfile import PlyData

    folder, scene, cams, _ = user_scene_files(tmp_path / "scene", 4, 40, 30)
    data = PlyData.read(str(scene))
    data["vertex"].data["opacity"][0] = -1e30
    data.write(str(tmp_path / "extreme.ply"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's overflow warning with a source line, no more
        assert main(["info", str(tmp_path / "extreme.ply")]) == 0
    behind = json.loads((folder / "transforms.json").read_text())
    for frame in behind["frames"]:
        frame["transform_matrix"][0][3] += 1e4  # every camera far away, looking at nothing
    (tmp_path / "away.json").write_text(json.dumps(behind))
    assert (
        main(
            [
                "render",
                str(scene),
                "--cameras",
                str(tmp_path / "away.json"),
                "--out",
                str(tmp_path / "v.png"),
            ]
        )
        == 0
    )
    assert "shows almost nothing of the scene" in capsys.readouterr().err


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "sagonline", *args], cwd=ROOT, capture_output=True, text=True
    )


def test_render_out_never_destroys_an_input(tmp_path, tiny_task, capsys):
    from types import SimpleNamespace

    from sagonline.apps.cli import main

    def _cli(*args):  # in this process: eight commands cost 20 s as subprocesses
        capsys.readouterr()
        code = main(list(args))
        return SimpleNamespace(returncode=code, stderr=capsys.readouterr().err)

    ply = write_ply(tmp_path / "scene.ply", tiny_task.gaussians)
    cams = write_3dgs_cameras_json(tmp_path / "cameras.json", tiny_task.trajectory[:1])
    before = ply.read_bytes()
    disguised = tmp_path / "scene.npy"  # a PLY under a name --out accepts
    disguised.write_bytes(before)
    for out, why in ((disguised, "one of the inputs"), (ply, "one of the inputs")):
        r = _cli("render", str(out), "--cameras", str(cams), "--out", str(out))
        assert r.returncode != 0 and why in r.stderr, r.stderr
    assert ply.read_bytes() == before == disguised.read_bytes()
    r = _cli("render", str(ply), "--cameras", str(cams), "--out", str(tmp_path / "view.ply"))
    assert r.returncode == 2 and "use a .png" in r.stderr
    png = tmp_path / "view.png"
    assert _cli("render", str(ply), "--cameras", str(cams), "--out", str(png)).returncode == 0
    r = _cli("render", str(ply), "--cameras", str(cams), "--out", str(png))
    assert "exists; pass --overwrite" in r.stderr
    (tmp_path / "gaussians").mkdir()
    ply.rename(tmp_path / "gaussians" / "point_cloud.ply")  # a folder is taken as its scene
    assert _cli("info", str(tmp_path)).returncode == 0
    r = _cli("info", str(tmp_path / "gaussians" / "nothing_here"))
    assert r.returncode == 2 and "not found" in r.stderr


def test_render_draws_on_the_colour_the_scene_was_fitted_on(tmp_path, capsys):
    """Without --background, a scene with a fit_config.json of white beside it renders on white
    (as `segment` renders its frames); --background still decides where given."""
    folder, scene, _, _ = user_scene_files(tmp_path / "scene", 4, 40, 30)
    cams = folder / "transforms.json"

    def shown(name: str, *extra: str) -> np.ndarray:
        out = tmp_path / f"{name}.png"
        argv = ["render", str(scene), "--cameras", str(cams), "--out", str(out), *extra]
        assert main(argv) == 0, capsys.readouterr().err
        return np.asarray(Image.open(out).convert("RGB")).astype(int)

    black = shown("black")
    (folder / "fit_config.json").write_text('{"background": [1.0, 1.0, 1.0]}')
    white, asked = shown("white"), shown("asked", "--background", "0,0,0")
    empty = black.max(-1) == 0
    assert empty.mean() > 0.01 and (white[empty] == 255).all()
    assert (asked == black).all()
