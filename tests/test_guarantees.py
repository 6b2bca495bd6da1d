"""The guarantees of `segment`, `export`, `render` and `sagonline score` (the surfaces an
adversarial new user found holes in): a run folder runs no code, nothing outside --out is
touched, a cache entry knows what it is, masks are read as what they are, and the scorer cannot
be fooled.
One test per hole found; each failed on the code before the fix."""

from __future__ import annotations

import json
import os
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from sagonline.apps.cli import main
from tests.fixtures import cfg_with, own_scene, tree_digest


@pytest.fixture(scope="module")
def user_scene(tmp_path_factory):
    """A user's scene folder (point_cloud.ply, transforms.json, notes.txt) and a click on its
    object in view 0."""
    folder, scene, cams, gt = own_scene(tmp_path_factory.mktemp("user") / "scene")
    inner = cv2.erode((gt == 1).astype(np.uint8), np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(inner)
    click = f"0:{xs[len(xs) // 2] + 0.5},{ys[len(xs) // 2] + 0.5}"
    return folder, click


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


def _one_line_error(capsys, *words) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err
    return err


# --- 1. a run folder never runs code ----------------------------------------------------------


def test_export_builds_nothing_named_by_the_run_folder(tmp_path, capsys):
    """The planted `.pth` writer: a run folder whose metrics.json names a class (and
    arguments) for the dataset. Export refuses it and writes nothing."""
    target = tmp_path / "site" / "zz.pth"
    run = tmp_path / "run"
    run.mkdir()
    planted = {
        "_target_": "sagonline.core.files.atomic_write_text",
        "_args_": [str(target), "import os; os.system('touch /tmp/owned')"],
    }
    for node in ({"adapter": planted}, {"kind": "generic", "adapter": planted}, planted):
        metrics = {
            "config": {"dataset": node, "segmenter": {"kind": "oracle"}, "consensus": {}},
            "scenes": [],
        }
        (run / "metrics.json").write_text(json.dumps(metrics))
        assert main(["export", str(run)]) == 2
        _one_line_error(capsys)
        assert not target.exists() and not (tmp_path / "site").exists()


def test_a_segmenter_config_outside_its_package_is_refused(tmp_path):
    """sam2's model config is instantiated: it must be the package's own file."""
    from sagonline.segment.sam2_video import package_config

    pkg = tmp_path / "sam2"
    (pkg / "configs").mkdir(parents=True)
    (tmp_path / "evil.yaml").write_text("model: {_target_: os.system}\n")
    for name in (str(tmp_path / "evil.yaml"), "../evil.yaml", "configs/../../evil.yaml"):
        with pytest.raises(ValueError, match="under the sam2 package's configs"):
            package_config(pkg, name)
    # and inside the package's own file, only sam2's classes are built
    from omegaconf import OmegaConf

    from sagonline.segment.sam2_video import check_targets

    check_targets(OmegaConf.create({"_target_": "sam2.modeling.X", "a": [{"_target_": "sam2.Y"}]}))
    planted = OmegaConf.create({"_target_": "sam2.X", "parts": [{"_target_": "os.system"}]})
    with pytest.raises(ValueError, match=r"model.parts\[0\]._target_='os.system'"):
        check_targets(planted)


# --- 2. nothing outside --out is lost ---------------------------------------------------------


@pytest.mark.parametrize("out", ["{folder}", "{folder}/point_cloud.ply", "{folder}/.."])
def test_segment_never_writes_over_its_inputs(user_scene, out, capsys):
    folder, click = user_scene
    before = tree_digest(folder.parent)
    for overwrite in ([], ["--overwrite"]):
        code = _segment(folder, "--click", click, "--out", out.format(folder=folder), *overwrite)
        assert code == 2
        err = _one_line_error(capsys, "input")
        assert "--overwrite" not in err.split("input")[1]  # never invited to replace an input
    assert tree_digest(folder.parent) == before
    assert not list(folder.parent.glob(".*tmp*"))


def test_overwrite_replaces_only_what_the_tool_wrote(user_scene, tmp_path, capsys):
    folder, click = user_scene
    mine = tmp_path / "my_results"
    mine.mkdir()
    (mine / "thesis.tex").write_text("months of work")
    assert _segment(folder, "--click", click, "--out", str(mine), "--overwrite") == 2
    _one_line_error(capsys, "did not write", "never replaced")
    assert (mine / "thesis.tex").read_text() == "months of work"
    out = tmp_path / "seg"
    assert _segment(folder, "--click", click, "--out", str(out)) == 0
    capsys.readouterr()  # the run's own progress lines
    assert (out / ".sagonline-output.json").is_file()
    assert _segment(folder, "--click", click, "--out", str(out)) == 2
    _one_line_error(capsys, "pass --overwrite")
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
    _one_line_error(capsys, message)
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


# --- 3. no wrong numbers without a message ----------------------------------------------------


def test_a_cache_entry_under_another_key_is_never_used(tmp_path, tiny_task):
    """A valid vote entry copied over another key's file: refused, removed, recomputed."""
    import warnings

    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    settings = PipelineSettings(progress=False)
    seg = OracleSegmenter()
    strict = VoteConfig(margin=0.9)
    a, _ = run_scene(tiny_task, seg, VoteConfig(), settings, cache_dir=tmp_path)
    b, _ = run_scene(tiny_task, seg, strict, settings, cache_dir=tmp_path)
    a_file = tmp_path / f"vote-{a.stage_keys['vote']}.store"
    b_file = tmp_path / f"vote-{b.stage_keys['vote']}.store"
    shutil.copy(a_file, b_file)  # b's key now holds a's vote
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        again, _ = run_scene(tiny_task, seg, strict, settings, cache_dir=tmp_path)
    assert again.stages["vote"] == "computed" and again.miou == b.miou
    assert any("not {'stage': 'vote'" in str(w.message) for w in caught)
    masks = next(tmp_path.glob("masks-*.store"))
    shutil.copy(masks, b_file)  # a masks entry under a vote key: removed, never a crash
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        once, _ = run_scene(tiny_task, seg, strict, settings, cache_dir=tmp_path)
        twice, _ = run_scene(tiny_task, seg, strict, settings, cache_dir=tmp_path)
    assert (once.stages["vote"], twice.stages["vote"]) == ("computed", "cached")
    assert once.miou == twice.miou == b.miou


@pytest.mark.parametrize("kind", ["file", "loop", "readonly"])
def test_an_unusable_cache_folder_warns_once_and_the_run_goes_on(
    tmp_path, tiny_task, kind, monkeypatch
):
    import warnings

    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    cache = tmp_path / "cache"
    if kind == "file":
        cache.write_text("not a folder")
    elif kind == "loop":
        os.symlink(cache, cache)
    else:  # read-only (root writes anyway: the writes themselves are made to fail)
        from sagonline.core import store

        cache.mkdir()
        cache.chmod(0o500)

        def denied(*args, **kwargs):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(store, "save", denied)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report, _ = run_scene(
            tiny_task,
            OracleSegmenter(),
            VoteConfig(),
            PipelineSettings(progress=False),
            cache_dir=cache,
        )
    assert report.miou is not None and report.miou > 0.5
    unusable = [w for w in caught if "is unusable" in str(w.message)]
    assert len(unusable) == 1, [str(w.message) for w in caught]


def test_export_redoes_a_vote_whose_recorded_key_lies(tmp_path, capsys):
    """metrics.json's vote key, pointed at another config's cached vote: export keys the vote
    again from the run's settings and exports the labels that belong to them."""
    from bench.runners.eval import evaluate
    from sagonline.labels.export import read_labels

    cache = tmp_path / "cache"
    runs = {}
    for name, margin in (("a", 0.2), ("b", 0.9)):
        cfg = cfg_with(
            "dataset=synthetic_ff",
            "record=false",
            f"consensus.margin={margin}",
            f"cache_dir={cache}",
        )
        runs[name] = evaluate(cfg, tmp_path / name)
    metrics_a = json.loads((tmp_path / "a" / "metrics.json").read_text())
    honest = metrics_a["scenes"][0]["stage_keys"]["vote"]
    metrics_a["scenes"][0]["stage_keys"]["vote"] = runs["b"]["scenes"][0]["stage_keys"]["vote"]
    (tmp_path / "a" / "metrics.json").write_text(json.dumps(metrics_a))
    assert main(["export", str(tmp_path / "a"), "--out", str(tmp_path / "a_export")]) == 0
    err = capsys.readouterr().err
    assert "is not the one the run recorded" in err
    labels, info = read_labels(tmp_path / "a_export" / "forward_single")
    assert info["stage_keys"]["vote"] == honest
    assert main(["export", str(tmp_path / "b"), "--out", str(tmp_path / "b_export")]) == 0
    other, _ = read_labels(tmp_path / "b_export" / "forward_single")
    assert not np.array_equal(labels, other)  # margin 0.9 leaves more unlabelled


@pytest.mark.parametrize(
    ("make", "kind", "objects"),
    [
        ("binary", "binary", 1),
        ("antialiased", "binary", 1),
        ("jpeg", "binary", 1),
        ("rgba_cutout", "binary", 1),
        ("grey_as_rgb", "binary", 1),
        ("labels", "label map", 2),
        ("labels_void", "label map", 3),
    ],
)
def test_masks_are_read_as_what_they_are(tmp_path, make, kind, objects):
    from sagonline.scene.io.masks import read_mask

    disc = np.zeros((60, 80), np.uint8)
    cv2.circle(disc, (40, 30), 15, 255, -1)
    labels = np.zeros((60, 80), np.uint8)
    labels[5:20, 5:20], labels[30:50, 40:70] = 1, 2
    image = {
        "binary": disc,
        "antialiased": cv2.GaussianBlur(disc, (9, 9), 2.0),
        "jpeg": disc,
        "rgba_cutout": np.dstack([np.full((60, 80, 3), 200, np.uint8), disc]),
        "grey_as_rgb": np.dstack([disc] * 3),
        "labels": labels,
        "labels_void": np.where(np.arange(60)[:, None] < 3, 255, labels).astype(np.uint8),
    }[make]
    path = tmp_path / ("m.jpg" if make == "jpeg" else "m.png")
    cv2.imwrite(str(path), image)
    read = read_mask(path)
    assert read.kind == kind
    assert len(np.unique(read.labels)) - 1 == objects
    if kind == "binary":
        assert abs(int(read.labels.sum()) - int((disc > 127).sum())) <= 30


@pytest.mark.parametrize(
    ("image", "seen"),
    [
        (np.random.default_rng(0).integers(0, 255, (30, 40, 3)).astype(np.uint8), "3 channels"),
        (
            np.dstack(
                [
                    np.random.default_rng(1).integers(0, 9, (30, 40, 3)).astype(np.uint8),
                    np.full((30, 40), 255, np.uint8),
                ]
            ),
            "4 channels",
        ),
        (np.arange(1200, dtype=np.uint16).reshape(30, 40), "1200 distinct values"),
    ],
)
def test_a_file_that_is_no_mask_is_refused_with_what_was_seen(tmp_path, image, seen):
    from sagonline.scene.io.masks import MaskFileError, read_mask

    cv2.imwrite(str(tmp_path / "m.png"), image)
    with pytest.raises(MaskFileError, match=seen):
        read_mask(tmp_path / "m.png")


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


def test_duplicate_camera_names_are_refused(tmp_path, capsys):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras
    from tests.fixtures import orbit_cameras, write_nerf_transforms

    cams = orbit_cameras(4)
    write_nerf_transforms(tmp_path / "t.json", cams, ["a", "b", "a", "c"])
    with pytest.raises(CameraFileError, match="frames 0 and 2 are both named 'a'"):
        load_cameras(tmp_path / "t.json")


# --- the scorer -------------------------------------------------------------------------------


def _label_maps(folder, scene="s", views=None, **files):
    for view, image in (views or files).items():
        path = folder / scene / f"{view}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), image)


def _score(*args):
    from sagonline.apps.cli.score import main as score

    return score([str(a) for a in args])


def test_the_scorer_cannot_be_fooled(tmp_path, capsys):
    gt = np.zeros((40, 60), np.uint8)
    gt[10:30, 20:40] = 1
    _label_maps(tmp_path / "gt", v0=gt)
    _label_maps(tmp_path / "tiny", v0=np.zeros((2, 3), np.uint8))  # the aspect of 40x60
    _label_maps(tmp_path / "wide", v0=np.zeros((40, 90), np.uint8))
    _label_maps(tmp_path / "half", v0=cv2.resize(gt, (30, 20), interpolation=cv2.INTER_NEAREST))
    for pred, flags, message in (
        ("tiny", ["--resize", "gt_to_pred"], "smaller than the ground truth"),
        ("wide", ["--resize", "pred_to_gt"], "other aspect ratios"),
        ("half", [], "give a resize rule"),
    ):
        with pytest.raises(SystemExit) as exc:
            _score(tmp_path / pred, tmp_path / "gt", *flags)
        assert exc.value.code == 2
        _one_line_error(capsys, message)
    assert _score(tmp_path / "half", tmp_path / "gt", "--resize", "pred_to_gt")["miou"] == 1.0


def test_a_view_that_is_all_ignored_is_skipped_not_perfect(tmp_path, capsys):
    gt = np.zeros((20, 20), np.uint8)
    gt[5:15, 5:15] = 1
    void = np.full((20, 20), 255, np.uint8)
    _label_maps(tmp_path / "gt", v0=gt, v1=void)
    _label_maps(tmp_path / "pred", v0=np.zeros_like(gt), v1=np.zeros_like(gt))
    result = _score(tmp_path / "pred", tmp_path / "gt", "--ignore", "255")
    assert result["miou"] == 0.0 and result["views"] == 1
    assert result["skipped_views"] == ["s/v1"]
    assert "skipped 1 view" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("rules", "message"),
    [
        ({"ignore_label": "255"}, "ignore_label must be an integer"),
        ({"ignore_label": True}, "ignore_label must be an integer"),
        ({"resize": "stretch"}, "resize 'stretch' is not one of"),
        ({"protocol_id": 3}, "protocol_id must be a string"),
        ({"ignore": 255}, "unknown key 'ignore'"),
        ([1, 2], "holds a list, not an object"),
    ],
)
def test_scoring_rules_are_checked_against_their_schema(tmp_path, rules, message, capsys):
    _label_maps(tmp_path / "gt", v0=np.zeros((8, 8), np.uint8))
    _label_maps(tmp_path / "pred", v0=np.zeros((8, 8), np.uint8))
    (tmp_path / "gt" / "scoring.json").write_text(json.dumps(rules))
    with pytest.raises(SystemExit):
        _score(tmp_path / "pred", tmp_path / "gt")
    _one_line_error(capsys, message)


def test_the_scorer_checks_a_runs_digests(tmp_path, capsys):
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    metrics = evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    result = _score(run)
    assert result["matches_run"] is True and abs(result["miou"] - metrics["miou"]) < 1e-12
    assert "predictions: match" in capsys.readouterr().out
    some = next((run / "predictions").rglob("*.png"))
    cv2.imwrite(str(some), np.zeros_like(cv2.imread(str(some), cv2.IMREAD_UNCHANGED)))
    with pytest.raises(SystemExit) as exc:  # and the numbers it records no longer hold
        _score(run)
    out = capsys.readouterr().out
    assert exc.value.code == 3 and "predictions: DO NOT MATCH" in out
    assert "CONTRADICTED by the re-score" in out


# --- run folders ------------------------------------------------------------------------------


@pytest.mark.slow
def test_an_overwritten_run_folder_keeps_nothing_of_the_old_config(tmp_path):
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    evaluate(cfg_with("dataset=synthetic_ff", "record=true"), run)
    assert main(["export", str(run), "--out", str(run / "export")]) == 0  # one's own choice
    assert (run / "export").is_dir() and (run / "recording.rrd").is_file()
    evaluate(
        cfg_with("dataset=synthetic_ff", "record=false", "consensus.eps=0.1", "overwrite=true"), run
    )
    assert not (run / "export").exists() and not (run / "recording.rrd").exists()
    assert json.loads((run / "metrics.json").read_text())["consensus"]["eps"] == 0.1
    assert not list(tmp_path.glob(".run.replaced-*"))


def test_a_second_run_into_a_locked_folder_is_refused(tmp_path, capsys):
    from bench.runners.eval import evaluate
    from sagonline.core.outputs import RunLock

    run = tmp_path / "run"
    with RunLock(run), pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    assert exc.value.code == 2
    _one_line_error(capsys, "another run is writing into this folder")
    assert not (run / "metrics.json").exists()


def test_a_misspelt_key_with_a_plus_is_refused(capsys):
    for override in ("+consensus.epss=0.05", "+segmenter.flickr=0.1", "+dataset.adapter.x=1"):
        with pytest.raises(SystemExit):
            cfg_with(override)
        _one_line_error(capsys, "no such setting")


@pytest.mark.slow
def test_a_refused_run_leaves_no_folder(tmp_path):
    import subprocess
    import sys

    from tests.fixtures import ROOT

    run = tmp_path / "run"
    done = subprocess.run(
        [sys.executable, "-m", "bench.runners.eval", "consensus.eps=2", f"hydra.run.dir={run}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "consensus.eps=2.0" in done.stderr
    assert not run.exists()


# --- 4 and 5: one line that names the key, file or flag ---------------------------------------


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
    _one_line_error(capsys, message)


def test_export_of_a_metrics_list_is_one_line(tmp_path, capsys):
    (tmp_path / "metrics.json").write_text("[1, 2]")
    assert main(["export", str(tmp_path)]) == 2
    _one_line_error(capsys, "holds a list, not a JSON object")


def test_segment_takes_drop_nonfinite_as_its_message_says(user_scene, tmp_path, capsys):
    from plyfile import PlyData

    folder, click = user_scene
    data = PlyData.read(str(folder / "point_cloud.ply"))
    data["vertex"].data["x"][3] = np.nan
    bad = tmp_path / "bad"
    shutil.copytree(folder, bad)
    data.write(str(bad / "point_cloud.ply"))
    assert _segment(bad, "--click", click, "--out", str(tmp_path / "o")) == 2
    assert "--drop-nonfinite" in _one_line_error(capsys)
    assert _segment(bad, "--click", click, "--out", str(tmp_path / "o"), "--drop-nonfinite") == 0


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("dataset.adapter.forward_single.width=0", "dataset.adapter.forward_single.width=0"),
        ("dataset.adapter.forward_single.width=-5", "dataset.adapter.forward_single.width=-5"),
        ("dataset.adapter.cluttered_360.width=100000", "cluttered_360.width=100000"),
        ("dataset.adapter.forward_single.num_train_views=0", "num_train_views=0"),
        ("dataset.adapter.forward_single.num_gaussians=0", "num_gaussians=0"),
        ("consensus.delta=inf", "consensus.delta=inf"),
        ("consensus.eps=nan", "consensus.eps=nan"),
    ],
)
def test_settings_out_of_range_name_their_key(override, key, capsys):
    with pytest.raises(SystemExit):
        cfg_with(override)
    _one_line_error(capsys, key)


def test_metrics_are_strict_json():
    from sagonline.core.files import to_json

    text = to_json({"a": float("nan"), "b": [float("inf"), 1.5], "c": np.float32(2)})
    assert json.loads(text) == {"a": None, "b": [None, 1.5], "c": 2.0}
    assert "NaN" not in text and "Infinity" not in text


def _transforms(tmp_path, **changes):
    from tests.fixtures import orbit_cameras, write_nerf_transforms

    path = write_nerf_transforms(tmp_path / "transforms.json", orbit_cameras(3))
    meta = json.loads(path.read_text())
    for key, value in changes.items():
        if key == "matrix3x4":
            for f in meta["frames"]:
                f["transform_matrix"] = f["transform_matrix"][:3]
        else:
            meta[key] = value
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"fl_x": "500"}, "fl_x='500' is not a number"),
        ({"w": True}, "is not a whole number of pixels"),
        ({"w": 32.5}, "is not a whole number of pixels"),
        ({"frames": {"a": 1}}, "'frames' must be a non-empty list"),
    ],
)
def test_camera_files_are_refused_naming_the_field(tmp_path, changes, message):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras

    with pytest.raises(CameraFileError, match=message):
        load_cameras(_transforms(tmp_path, **changes))


def test_a_3x4_transform_matrix_is_read(tmp_path):
    from sagonline.scene.io.cameras import load_cameras

    full = load_cameras(_transforms(tmp_path))
    short = load_cameras(_transforms(tmp_path, matrix3x4=True))
    for a, b in zip(full, short, strict=True):
        assert np.allclose(a.world_to_cam, b.world_to_cam)


def test_colmap_models_missing_images_or_with_a_zero_quaternion(tmp_path):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras
    from tests.fixtures import orbit_cameras, write_colmap_text

    write_colmap_text(tmp_path / "m", orbit_cameras(3))
    assert len(load_cameras(tmp_path / "m")) == 3
    lines = (tmp_path / "m" / "images.txt").read_text().splitlines()
    data = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")]
    parts = lines[data[0]].split()
    parts[1:5] = ["0", "0", "0", "0"]
    lines[data[0]] = " ".join(parts)
    (tmp_path / "m" / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(CameraFileError, match="no rotation"):
        load_cameras(tmp_path / "m")
    (tmp_path / "m" / "images.txt").unlink()
    with pytest.raises(CameraFileError, match="without images.bin or images.txt"):
        load_cameras(tmp_path / "m")


def test_a_camera_file_beyond_the_ceiling_is_refused_quickly(tmp_path):
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.io.cameras import load_cameras
    from sagonline.scene.io.pose import MAX_CAMERAS

    one = {"transform_matrix": np.eye(4).tolist(), "file_path": "x"}
    meta = {"fl_x": 50, "w": 64, "h": 48, "frames": [one] * (MAX_CAMERAS + 1)}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(CameraFileError, match="exceed the ceiling of 20,000"):
        load_cameras(tmp_path / "transforms.json")


@pytest.mark.parametrize("kind", ["file", "loop"])
def test_an_eval_with_an_unusable_cache_dir_finishes(tmp_path, kind):
    from bench.runners.eval import evaluate

    cache = tmp_path / "cache"
    if kind == "file":
        cache.write_text("not a folder")
    else:
        os.symlink(cache, cache)
    metrics = evaluate(
        cfg_with("dataset=synthetic_ff", "record=false", f"cache_dir={cache}"), tmp_path / "run"
    )
    assert metrics["status"] == "complete" and metrics["miou"] > 0.9
    assert "is unusable" in (tmp_path / "run" / "eval.log").read_text()  # warned, in the log


def test_overwrite_replaces_only_what_the_harness_wrote(tmp_path, capsys):
    """A file of the user's in a finished run folder survives overwrite=true, and is named
    (it was moved aside and deleted with the old run)."""
    from bench.runners.eval import evaluate

    run = tmp_path / "run"
    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    (run / "notes.txt").write_text("why this run matters")
    (run / "mine").mkdir()
    evaluate(
        cfg_with("dataset=synthetic_ff", "record=false", "consensus.eps=0.1", "overwrite=true"), run
    )
    assert (run / "notes.txt").read_text() == "why this run matters" and (run / "mine").is_dir()
    assert "kept what the harness did not write: mine, notes.txt" in capsys.readouterr().err


def test_export_writes_beside_the_run_not_into_it(tmp_path, monkeypatch):
    """`sagonline export RUN` leaves the finished run's folder as the run wrote it: the default
    output is export-<parent>-<run> in the current folder."""
    from bench.runners.eval import evaluate
    from tests.fixtures import tree_digest

    run = tmp_path / "runs" / "r1"
    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), run)
    before = tree_digest(run)
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(run)]) == 0
    assert tree_digest(run) == before
    assert (tmp_path / "export-runs-r1" / "forward_single" / "labels.npy").is_file()
