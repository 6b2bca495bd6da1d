"""The command line users and checks rely on."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from tests.fixtures import shared_data


def _run(*args):
    return subprocess.run(
        [sys.executable, "-m", "sagonline", *args], capture_output=True, text=True
    )


@pytest.mark.slow
def test_info_prints_format_count_degree_bbox():
    res = _run("info", str(shared_data("sh3_scene_3dgs", "point_cloud.ply")))
    assert res.returncode == 0, res.stderr
    assert "gaussians:   9080" in res.stdout and "sh degree:   3" in res.stdout
    assert "bbox min:" in res.stdout and "ply" in res.stdout


@pytest.mark.slow
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


@pytest.mark.slow
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


def test_one_view_numbering_for_every_command(tmp_path, capsys):
    """Frames r_0 .. r_11 listed in file order: index 2 is r_10 (cameras sorted by name) for
    `cameras`, `render --view`, `segment --preview` and `segment --click` alike."""
    from sagonline.apps.cli import main
    from tests.fixtures import own_scene

    folder, *_ = own_scene(tmp_path / "scene", views=12)
    ply, cams = str(folder / "point_cloud.ply"), str(folder / "transforms.json")
    assert main(["cameras", cams]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert "with --orbit N" in listed[-1] and "'r_0'" in listed[-1]  # which numbering holds
    rows = [line.split() for line in listed[2:-1]]
    assert [r[:2] for r in rows[:5]] == [
        ["0", "r_0"],
        ["1", "r_1"],
        ["2", "r_10"],
        ["3", "r_11"],
        ["4", "r_2"],
    ]
    for view in ("2", "r_10", "r_2"):
        assert (
            main(
                [
                    "render",
                    ply,
                    "--cameras",
                    cams,
                    "--view",
                    view,
                    "--out",
                    str(tmp_path / f"{view}.png"),
                ]
            )
            == 0
        )
    by_index, by_name = (np.asarray(Image.open(tmp_path / f"{v}.png")) for v in ("2", "r_10"))
    assert np.array_equal(by_index, by_name)
    assert not np.array_equal(by_index, np.asarray(Image.open(tmp_path / "r_2.png")))
    assert (
        main(
            [
                "segment",
                ply,
                "--cameras",
                cams,
                "--preview",
                "2",
                "--out",
                str(tmp_path / "preview.png"),
            ]
        )
        == 0
    )
    assert "view 2 'r_10' at 48x36" in capsys.readouterr().out
    preview = np.asarray(Image.open(tmp_path / "preview.png").convert("RGB")).astype(int)
    other = np.asarray(Image.open(tmp_path / "r_2.png")).astype(int)
    same = (np.abs(preview - by_index).max(-1) <= 2).mean()  # the same view under a light grid
    assert same > 0.8 and same > (np.abs(preview - other).max(-1) <= 2).mean() + 0.3, same
    out = tmp_path / "seg"
    assert (
        main(
            [
                "segment",
                ply,
                "--cameras",
                cams,
                "--click",
                "2:24,18",
                "--out",
                str(out),
                "--no-record",
            ]
        )
        == 0
    )
    prompt = json.loads((out / "labels.json").read_text())["prompt"]
    assert (prompt["view"], prompt["view_name"], prompt["render_size"]) == (2, "r_10", [48, 36])


def test_the_preview_shows_the_views_on_the_colour_the_segmenter_sees(tmp_path, capsys):
    """A scene fitted on white (fit_config.json beside it, as `make scenes` writes) is
    previewed on white, as `segment` renders its frames: one view and the contact sheet."""
    from sagonline.apps.cli import main
    from tests.fixtures import own_scene

    folder, *_ = own_scene(tmp_path / "scene", views=4)
    ply, cams = str(folder / "point_cloud.ply"), str(folder / "transforms.json")
    shown = {}
    for colour in ("black", "white"):
        if colour == "white":
            (folder / "fit_config.json").write_text('{"background": [1.0, 1.0, 1.0]}')
        for view in ("0", "all"):
            out = tmp_path / f"{colour}_{view}.png"
            argv = ["segment", ply, "--cameras", cams, "--preview", view, "--out", str(out)]
            assert main(argv) == 0, capsys.readouterr().err
            shown[colour, view] = np.asarray(Image.open(out).convert("RGB")).astype(int)
    for view in ("0", "all"):
        black, white = shown["black", view], shown["white", view]
        empty = black.max(-1) == 0  # nothing of the scene, no grid line, no tile label there
        if view == "all":
            empty[:16] = False  # the sheet's strip of tile labels: black on both
        assert empty.mean() > 0.01 and (white[empty] == 255).all(), view


def test_the_overview_and_a_light_commands_help_import_no_torch():
    """`sagonline --help`, no command, a misspelt one, `--help` of every command, and a choice
    `segment` refuses build only what they show: PyTorch (about 2 s) is not imported, nor OpenCV
    where nothing shown needs it (the segmenters' and vote methods' names and settings are
    read from their declarations), and the overview lists every command with the line the full
    parser gives it."""
    import subprocess
    import sys

    from sagonline.apps.cli import build_parser
    from tests.fixtures import ROOT

    code = (
        "import sys\n"
        "from sagonline.apps.cli import main\n"
        "try:\n"
        "    status = main(sys.argv[1:])\n"
        "except SystemExit as exc:\n"
        "    status = exc.code\n"
        "heavy = sorted(m for m in ('torch', 'cv2') if m in sys.modules)\n"
        "print('imported:', heavy, 'status:', status, file=sys.stderr)\n"
    )
    torch_only = (["--help"], 0), ([], 2), (["rendr", "x"], 2), (["info", "--help"], 0)
    torch_only += (["render", "--help"], 0), (["figure", "--help"], 0), (["score", "--help"], 0)
    neither = (["segment", "--help"], 0), (["view", "--help"], 0)
    neither += ((["segment", "s.ply", "--method", "nope"], 2),)
    neither += ((["view", "s.ply", "--segmenter", "nope"], 2),)
    for argv, status in torch_only + neither:
        run = subprocess.run(
            [sys.executable, "-c", code, *argv], cwd=ROOT, capture_output=True, text=True
        )
        last = run.stderr.splitlines()[-1]
        heavy = last.partition(" status")[0]
        assert last.endswith(f"status: {status}"), (argv, run.stderr)
        assert "torch" not in heavy, (argv, run.stderr)
        assert (argv, status) not in neither or "cv2" not in heavy, (argv, run.stderr)
    assert build_parser(["--help"]).format_help() == build_parser().format_help()


def test_render_defaults_to_the_backend_everything_else_takes():
    """`sagonline render` defaults to backend auto (it said torch) and device auto, as
    `segment`, `view` and the evaluation do."""
    from sagonline.apps.cli import build_parser

    parser = build_parser()
    for command in (["render", "s.ply", "--out", "x.png"], ["segment", "s.ply"], ["view", "s.ply"]):
        args = parser.parse_args(command)
        assert (args.backend, args.device) == ("auto", "auto"), command


def test_segment_takes_every_vote_setting_from_the_command_line():
    """--weighting reaches the vote's settings like --eps and --delta; a value the vote refuses
    is named as the flag."""
    from sagonline.apps.cli import build_parser
    from sagonline.apps.cli.options import vote_config

    args = build_parser().parse_args(["segment", "s.ply", "--weighting", "blend", "--delta", "3"])
    cfg = vote_config(args)
    assert (cfg.weighting, cfg.delta, cfg.method) == ("blend", 3.0, "rgc")
    assert cfg.rule.weighting == "blend"
    args = build_parser().parse_args(
        ["segment", "s.ply", "--weighting", "blend", "--method", "flashsplat"]
    )
    with pytest.raises(ValueError, match="--weighting"):
        vote_config(args)
    args = build_parser().parse_args(["segment", "s.ply", "--body"])
    assert vote_config(args).body is True
    assert vote_config(build_parser().parse_args(["segment", "s.ply"])).body is False


def test_every_vote_methods_setting_is_a_flag_generated_from_its_dataclass():
    """Each registered method's settings are flags (typed from their fields); --delta none turns
    the distance rule off; a method's setting given to another method is refused, named."""
    from dataclasses import fields

    from sagonline.apps.cli import build_parser
    from sagonline.apps.cli.options import vote_config
    from sagonline.core.plugins import VOTE_RULES

    parser = build_parser()
    for plugin in VOTE_RULES:
        for f in fields(plugin.config):
            value = {"weighting": "blend", "delta": "none"}.get(f.name, "0.5")
            if f.name == "min_votes":
                value = "3"
            flag = f"--{f.name.replace('_', '-')}"
            args = parser.parse_args(["segment", "s.ply", "--method", plugin.key, flag, value])
            cfg = vote_config(args)
            expected = None if value == "none" else f.type != "str" and float(value) or value
            assert getattr(cfg, f.name) == expected, (plugin.key, f.name)
            assert getattr(cfg.settings(), f.name) == expected
    args = parser.parse_args(["segment", "s.ply", "--method", "rgc", "--threshold", "0.5"])
    with pytest.raises(ValueError, match="--threshold 0.5: the method rgc does not read"):
        vote_config(args)
    with pytest.raises(SystemExit):
        parser.parse_args(["segment", "s.ply", "--min-votes", "two"])


def test_segment_and_view_take_the_label_renders_threshold():
    """--min-weight (segment and view): the label renders' threshold, the pipeline's default
    when not given, refused out of [0, 1] naming the flag."""
    from sagonline.apps.cli import build_parser
    from sagonline.apps.cli.options import label_min_weight
    from sagonline.render.rule import LABEL_MIN_WEIGHT

    parser = build_parser()
    for command in ("segment", "view"):
        assert label_min_weight(parser.parse_args([command, "s.ply"])) == LABEL_MIN_WEIGHT
        assert label_min_weight(parser.parse_args([command, "s.ply", "--min-weight", "0.5"])) == 0.5
        with pytest.raises(ValueError, match=r"--min-weight -0.1: must be a blend weight"):
            label_min_weight(parser.parse_args([command, "s.ply", "--min-weight", "-0.1"]))


def test_a_scenes_own_cameras_are_found_beside_it(tmp_path, capsys):
    """A 3DGS training output (<model>/point_cloud/iteration_<N>/point_cloud.ply beside
    <model>/cameras.json) and a fit's folder (the camera file beside the PLY): render, segment
    and cameras take its views without --cameras, say where they came from and record the
    file; --cameras none gives the orbit; a labels.json recorded with none replays its orbit."""
    import shutil

    from sagonline.apps.cli import main
    from sagonline.scene.io.cameras import write_3dgs_cameras_json
    from tests.fixtures import own_scene

    folder, _, cams, _ = own_scene(tmp_path / "fit", views=4)
    model = tmp_path / "model"
    (model / "point_cloud" / "iteration_30").mkdir(parents=True)
    shutil.copy(folder / "point_cloud.ply", model / "point_cloud" / "iteration_30")
    write_3dgs_cameras_json(model / "cameras.json", cams)

    def render(*args: str) -> np.ndarray:
        out = tmp_path / f"{len(list(tmp_path.glob('*.png')))}.png"
        assert main(["render", *args, "--view", "r_2", "--out", str(out)]) == 0
        return np.asarray(Image.open(out))

    given = render(str(folder / "point_cloud.ply"), "--cameras", str(folder / "transforms.json"))
    assert "found beside" not in capsys.readouterr().out
    for scene, cameras in (
        (folder / "point_cloud.ply", "transforms.json"),
        (model, "cameras.json"),
    ):
        assert np.array_equal(render(str(scene)), given)
        said = capsys.readouterr().out
        assert f"cameras of {scene if scene.is_dir() else folder}/{cameras}" in said, said
        assert "(found beside the scene; --cameras none: an orbit around it)" in said
    none = [
        "render",
        str(model),
        "--cameras",
        "none",
        "--view",
        "r_2",
        "--out",
        str(tmp_path / "n.png"),
    ]
    assert main(none) == 2  # the orbit's views, orbit_000 ...
    assert "no view named 'r_2' (views: orbit_000 ... orbit_023" in capsys.readouterr().err
    (folder / "transforms.json").write_text("{}")  # a broken file beside: named, and the way out
    assert main(["render", str(folder / "point_cloud.ply"), "--out", str(tmp_path / "x.png")]) == 2
    assert "(found beside the scene, as no --cameras was given: --cameras none for an orbit" in (
        capsys.readouterr().err
    )
    assert main(["cameras", str(model / "point_cloud" / "iteration_30" / "point_cloud.ply")]) == 0
    assert f"4 cameras of {model}/cameras.json" in capsys.readouterr().out
    out = tmp_path / "seg"
    assert (
        main(["segment", str(model), "--click", "r_2:24,18", "--out", str(out), "--no-record"]) == 0
    )
    record = json.loads((out / "labels.json").read_text())
    assert record["cameras"] == str(model / "cameras.json") and record["prompt"]["view"] == 2
    assert "found beside the scene" in capsys.readouterr().err
    record["cameras"], record["prompt"]["view_name"] = None, "orbit_003"  # made without cameras
    (out / "labels.json").write_text(json.dumps(record))
    again = tmp_path / "again"
    argv = ["segment", str(model), "--prompts", str(out / "labels.json"), "--out", str(again)]
    assert main([*argv, "--no-record"]) == 0
    assert json.loads((again / "labels.json").read_text())["cameras"] is None
    assert "views: no --cameras given: an orbit" in capsys.readouterr().err
    single = tmp_path / "single"  # a camera file of one view: said, with the way to a ring
    single.mkdir()
    shutil.copy(folder / "point_cloud.ply", single)
    write_3dgs_cameras_json(single / "cameras.json", cams[:1])
    argv = ["segment", str(single), "--click", "0:24,18", "--out", str(tmp_path / "s1")]
    assert main([*argv, "--no-record"]) == 0
    assert "1 camera of" in (err := capsys.readouterr().err) and "one view only: --orbit N" in err
