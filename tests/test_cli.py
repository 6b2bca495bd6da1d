"""The command line users and checks rely on."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from PIL import Image

from tests.fixtures import shared_data


def _run(*args):
    return subprocess.run(
        [sys.executable, "-m", "sagonline", *args], capture_output=True, text=True
    )


def test_info_prints_format_count_degree_bbox():
    res = _run("info", str(shared_data("sh3_scene_3dgs", "point_cloud.ply")))
    assert res.returncode == 0, res.stderr
    assert "gaussians:   9080" in res.stdout and "sh degree:   3" in res.stdout
    assert "bbox min:" in res.stdout and "ply" in res.stdout


def test_render_png_and_npy(tmp_path):
    scene = shared_data("donut_3dgs", "point_cloud.ply")
    cams = shared_data("donut_3dgs", "transforms.json")

    def render_to(name):
        args = ["--cameras", str(cams), "--width", "96", "--height", "54"]
        return _run("render", str(scene), *args, "--out", str(tmp_path / name))

    res = render_to("d.npy")
    assert res.returncode == 0, res.stderr
    arr = np.load(tmp_path / "d.npy")
    assert arr.shape == (54, 96, 3) and arr.dtype == np.float32
    assert arr[0, 0].tolist() == [0, 0, 0]  # black background in a corner
    assert arr[:27].max() > 0.3  # the donut sits in the upper half
    res = render_to("d.png")
    assert res.returncode == 0, res.stderr
    png = np.asarray(Image.open(tmp_path / "d.png"))
    assert png.shape == (54, 96, 3)
    assert np.abs(png / 255.0 - arr.clip(0, 1)).max() < 1 / 255 + 1e-6


def test_render_errors_name_the_problem(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    res = _run("info", str(bad))
    assert res.returncode == 2 and "bad.ply" in res.stderr
    res = _run(
        "render",
        str(shared_data("donut_3dgs", "point_cloud.ply")),
        "--cameras",
        str(shared_data("donut_3dgs", "transforms.json")),
        "--view",
        "5",
        "--out",
        str(tmp_path / "x.png"),
    )
    assert res.returncode != 0 and "out of range" in res.stderr
