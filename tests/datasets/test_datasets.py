"""Dataset adapters on tiny replicas of each layout, with the traps the protocols warn about."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from sagonline.datasets.base import DatasetError
from sagonline.datasets.generic import PosedMasksDataset
from sagonline.datasets.nvos import NVOSDataset
from sagonline.datasets.spinnerf import SPInNeRFDataset
from tests.fixtures import compose_config, llff_scene, object_mask, write_image

NAMES = [f"IMG_{i:04d}" for i in range(6)]


def _masks(folder: Path, cams, scene, names, suffix=".png", scale=1):
    for cam, name in zip(cams, names, strict=True):
        m = (object_mask(scene, cam) > 0).astype(np.uint8) * 255
        if scale != 1:
            m = cv2.resize(m, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        write_image(folder / f"{name}{suffix}", m)


def test_generic_binary_jpeg_masks_pseudo_and_missing_view(tmp_path):
    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    _masks(tmp_path / "cap" / "masks", cams[1:], scene, NAMES[1:], suffix=".jpg", scale=2)
    write_image(tmp_path / "cap" / "masks" / f"{NAMES[2]}_pseudo.png", np.zeros((48, 64), np.uint8))
    ds = PosedMasksDataset(tmp_path / "cap", image_dir="images_4", mask_dir="masks")
    assert ds.scene_names() == ["cap"]
    task = ds.load_scene("cap")
    assert [v.name for v in task.eval_views] == NAMES[1:]  # view 0 has no mask; pseudo skipped
    assert task.trajectory_gt is None  # not every frame has a mask
    assert task.meta["reference"] == NAMES[1] and task.prompt.frame == 1
    # JPEG ringing is thresholded away: masks are exactly 0/1 and match the render's object
    gt = task.eval_views[0].gt
    assert set(np.unique(gt)) == {0, 1} and gt.shape == (48, 64)
    obj = task.prompt.objects[0]
    want = object_mask(scene, cams[1]) > 0
    for x, y in obj.points:
        assert want[int(y), int(x)]


def test_generic_mask_aspect_mismatch_names_the_file(tmp_path):
    cams, scene = llff_scene(tmp_path / "cap", NAMES[:3])
    for n in NAMES[:3]:
        write_image(tmp_path / "cap" / "masks" / f"{n}.png", np.zeros((24, 24), np.uint8))
    with pytest.raises(DatasetError, match=r"IMG_0000\.png.*24x24.*32x24"):
        PosedMasksDataset(tmp_path / "cap", mask_dir="masks").load_scene("cap")


def test_generic_missing_trained_scene_says_where(tmp_path):
    cams, scene = llff_scene(tmp_path / "cap", NAMES[:3], with_scene=False)
    _masks(tmp_path / "cap" / "masks", cams, scene, NAMES[:3])
    with pytest.raises(DatasetError, match=r"expected .*cap/gaussians/point_cloud\.ply"):
        PosedMasksDataset(tmp_path / "cap", mask_dir="masks").load_scene("cap")


def test_generic_wrong_layout(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no data at"):
        PosedMasksDataset(tmp_path / "empty").scene_names()
    with pytest.raises(DatasetError, match="no data at"):
        PosedMasksDataset(tmp_path / "absent").scene_names()


def test_spinnerf_counts_cutout_orchids_and_reference(tmp_path):
    root = tmp_path / "spin"
    cams, scene = llff_scene(root / "fern", NAMES)
    _masks(root / "fern" / "labels", cams, scene, NAMES)
    write_image(root / "fern" / "labels" / f"{NAMES[0]}_cutout.png", np.zeros((24, 32), np.uint8))
    with pytest.raises(DatasetError, match="6 label maps, the protocol expects 20"):
        SPInNeRFDataset(root, scenes=["fern"]).load_scene("fern")
    ds = SPInNeRFDataset(root, scenes=["fern"], check_counts=False)
    task = ds.load_scene("fern")
    assert len(task.eval_views) == 6 and task.meta["reference"] == NAMES[0]
    assert task.trajectory_gt is not None and len(task.trajectory_gt) == 6
    excl = SPInNeRFDataset(root, scenes=["fern"], check_counts=False, exclude_reference=True)
    assert [v.name for v in excl.load_scene("fern").eval_views] == NAMES[1:]
    # orchids: one image without a mask is matched by name, not index
    cams2, scene2 = llff_scene(root / "orchids", NAMES)
    _masks(root / "orchids" / "labels", cams2[:2] + cams2[3:], scene2, NAMES[:2] + NAMES[3:])
    t2 = SPInNeRFDataset(root, scenes=["orchids"], check_counts=False).load_scene("orchids")
    assert [v.name for v in t2.eval_views] == NAMES[:2] + NAMES[3:]
    assert SPInNeRFDataset(root).describe()["resolutions"]["room"] == "images_8"
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "README.md").write_text("layout")
    with pytest.raises(DatasetError, match="no data at"):
        SPInNeRFDataset(tmp_path / "empty").scene_names()


def _nvos(tmp_path, drop_target=False):
    root = tmp_path / "nvos"
    target, ref = "DJI_20200223_163024_597", "DJI_20200223_163055_437"
    names = sorted([target, ref, "DJI_20200223_163100_000", "DJI_20200223_163000_000"])
    if drop_target:
        names = [n for n in names if n != target] + ["DJI_20200223_163200_000"]
        names.sort()
    cams, scene = llff_scene(root / "scenes" / "horns", names)
    by = {c.name: c for c in cams}
    for task in ("horns_center", "horns_left"):
        if not drop_target:
            m = (object_mask(scene, by[target]) > 0).astype(np.uint8) * 255
            write_image(root / "masks" / task / f"{target}_mask.png", m)
        write_image(root / "reference_image" / task / f"{ref}.JPG", np.zeros((24, 32, 3), np.uint8))
        scrib = np.zeros((24, 32), np.uint8)
        scrib[10:13, 12:20] = 255
        write_image(root / "scribbles" / task / "pos_0.png", scrib)
        write_image(root / "scribbles" / task / "vis_0.png", scrib)
    return root, names, target, ref


def test_nvos_horns_two_tasks_on_one_image(tmp_path):
    root, names, target, ref = _nvos(tmp_path)
    ds = NVOSDataset(root, tasks=["horns_center", "horns_left"])
    assert ds.scene_names() == ["horns_center", "horns_left"]
    a, b = ds.load_scene("horns_center"), ds.load_scene("horns_left")
    assert a.eval_views[0].name == b.eval_views[0].name == target
    assert a.prompt.frame == names.index(ref)
    pts = a.prompt.objects[0].points
    assert len(pts) == 16 and (pts[:, 1] > 9).all() and (pts[:, 1] < 14).all()
    clicks = NVOSDataset(root, tasks=["horns_center"], prompt="clicks").load_scene("horns_center")
    assert clicks.prompt.frame == names.index(target)


def test_nvos_scribbles_at_quarter_size_land_on_the_same_pixels(tmp_path):
    root, names, target, ref = _nvos(tmp_path)
    small = np.zeros((6, 8), np.uint8)  # the same scribble (rows 10-12, cols 12-19) at 1/4
    small[2:4, 3:5] = 255
    folder = root / "scribbles" / "horns_center"
    (folder / "pos_0.png").unlink()
    write_image(folder / "pos_3_horns.png", small)  # any numbering, a suffix
    pts = NVOSDataset(root, tasks=["horns_center"]).load_scene("horns_center")
    pts = pts.prompt.objects[0].points
    assert len(pts) == 4  # four scribble pixels, each at its 4x4 block's centre
    assert (pts[:, 0] >= 12).all() and (pts[:, 0] < 20).all()
    assert (pts[:, 1] >= 8).all() and (pts[:, 1] < 16).all()


def test_nvos_released_layout_with_colmap_undistort_scenes(tmp_path):
    from tests.fixtures import write_colmap_text

    flat, names, target, ref = _nvos(tmp_path)
    flat_task = NVOSDataset(flat, tasks=["horns_left"]).load_scene("horns_left")
    root = tmp_path / "release"
    labels = root / "labels" / "llff"
    labels.mkdir(parents=True)
    for part in ("masks", "reference_image"):
        (flat / part).rename(labels / part)
    (labels / "scribbles" / "horns_left").mkdir(parents=True)
    scribble = flat / "scribbles" / "horns_left" / "pos_0.png"
    scribble.rename(labels / "scribbles" / "horns_left" / "pos_0_horns.png")
    scene = root / "scenes" / "horns_undistort"  # COLMAP at the full size (4x the masks)
    write_colmap_text(scene / "sparse" / "0", flat_task.trajectory, scale=4)
    for n in names:
        write_image(scene / "images" / f"{n}.JPG", np.zeros((96, 128, 3), np.uint8))
    (flat / "scenes" / "horns" / "gaussians").rename(scene / "gaussians")
    task = NVOSDataset(root, tasks=["horns_left"]).load_scene("horns_left")
    assert [c.name for c in task.trajectory] == names
    for a, b in zip(task.trajectory, flat_task.trajectory, strict=True):  # scaled to the masks
        assert (a.width, a.height) == (b.width, b.height) == (32, 24)
        assert torch.allclose(a.K, b.K, atol=1e-4)
        assert torch.allclose(a.world_to_cam, b.world_to_cam, atol=1e-5)
    assert np.array_equal(task.eval_views[0].gt, flat_task.eval_views[0].gt)
    assert np.allclose(task.prompt.objects[0].points, flat_task.prompt.objects[0].points)
    # the captures kept elsewhere
    elsewhere = tmp_path / "captures"
    (root / "scenes").rename(elsewhere)
    with pytest.raises(DatasetError, match=r"(?s)labels/llff/masks.*scenes/<scene>/"):
        NVOSDataset(root, tasks=["horns_left"]).scene_names()
    moved = NVOSDataset(root, tasks=["horns_left"], scenes_root=elsewhere)
    assert moved.load_scene("horns_left").eval_views[0].name == target


def test_nvos_missing_target_view_and_missing_data(tmp_path):
    root, *_ = _nvos(tmp_path, drop_target=True)
    with pytest.raises(DatasetError, match="target view DJI_20200223_163024_597 is not among"):
        NVOSDataset(root, tasks=["horns_center"]).load_scene("horns_center")
    with pytest.raises(DatasetError, match=r"(?s)no data at .*datasets/nvos/README\.md"):
        NVOSDataset(tmp_path / "nothing").scene_names()


def test_kitti360_instances_renumbered_consistently(tmp_path):
    cams, scene = llff_scene(tmp_path / "seg", NAMES[:3])
    for i, n in enumerate(NAMES[:3]):
        m = np.zeros((24, 32), np.uint16)
        m[2:8, 2:8] = 26 * 1000 + 17  # car 17 everywhere
        m[10:14, 10:20] = 7 * 1000 + 3  # road: dropped
        if i > 0:
            m[15:20, 20:30] = 27 * 1000 + 4  # a truck from view 1 on
        write_image(tmp_path / "seg" / "instance" / f"{n}.png", m)
    ds = PosedMasksDataset(
        tmp_path / "seg",
        name="kitti360",
        mask_dir="instance",
        label_format="kitti360",
        prompt="none",
    )
    task = ds.load_scene("seg")
    assert task.num_labels == 3 and task.label_names == [
        "background",
        "instance_26017",
        "instance_27004",
    ]
    assert task.eval_views[0].gt[3, 3] == 1 and task.eval_views[2].gt[16, 22] == 2
    assert task.eval_views[1].gt[11, 12] == 0 and not task.prompt.objects


def test_palette_and_per_object_formats(tmp_path):
    cams, scene = llff_scene(tmp_path / "u", NAMES[:2])
    for n in NAMES[:2]:
        img = np.zeros((24, 32, 3), np.uint8)
        img[:, 16:] = (156, 102, 102)  # BGR of facade (102, 102, 156)
        write_image(tmp_path / "u" / "gt" / f"{n}.png", img)
    ds = PosedMasksDataset(
        tmp_path / "u",
        name="udd",
        mask_dir="gt",
        label_format="palette",
        palette={"0,0,0": 0, "102,102,156": 1},
        label_names=["other", "facade"],
        prompt="text",
    )
    task = ds.load_scene("u")
    assert task.eval_views[0].gt[0, 20] == 1 and task.prompt.texts == ["facade"]
    assert task.eval_views[0].gt.dtype == np.uint8 and task.eval_views[0].gt[0, 0] == 0
    wide = dataclasses.replace(ds.labels, palette={"0,0,0": 0, "102,102,156": 300})
    assert wide.read(tmp_path / "u" / "gt" / f"{NAMES[0]}.png").dtype == np.uint16
    img[0, 0] = (1, 2, 3)
    write_image(tmp_path / "u" / "gt" / f"{NAMES[0]}.png", img)
    with pytest.raises(DatasetError, match=r"colour \(3, 2, 1\) is not in the dataset palette"):
        ds.load_scene("u")
    cams, scene = llff_scene(tmp_path / "l", NAMES[:2])
    for n in NAMES[:2]:
        for obj, sl in (("bear", np.s_[0:5, 0:5]), ("cup", np.s_[10:15, 10:15])):
            m = np.zeros((24, 32), np.uint8)
            m[sl] = 255
            write_image(tmp_path / "l" / "test_mask" / n / f"{obj}.png", m)
    lerf = PosedMasksDataset(
        tmp_path / "l",
        name="lerf_mask",
        mask_dir="test_mask",
        label_format="per_object",
        prompt="text",
    ).load_scene("l")
    assert lerf.label_names == ["background", "bear", "cup"]
    assert lerf.eval_views[0].gt[12, 12] == 2 and lerf.prompt.texts == ["bear", "cup"]


def test_run_over_many_scenes_reports_the_broken_one(tmp_path):
    from bench.runners.eval import evaluate

    root = tmp_path / "data"
    for scene, with_scene in (("good", True), ("broken", False)):
        cams, sc = llff_scene(root / scene, NAMES[:4], with_scene=with_scene)
        _masks(root / scene / "masks", cams, sc, NAMES[:4])
    cfg = compose_config(
        "eval",
        *["dataset=generic", f"dataset.root={root}", "progress=false", "record=false"],
    )
    m = evaluate(cfg, tmp_path / "run")
    assert m["partial"] is True and m["scenes_failed"] == ["broken"]
    good = next(s for s in m["scenes"] if s["scene"] == "good")
    assert good["status"] == "ok" and good["miou"] > 0.5
    broken = next(s for s in m["scenes"] if s["scene"] == "broken")
    assert "gaussians/point_cloud.ply" in broken["error"]
    # the same partial run again: skipped; once the broken scene loads, refused until overwrite
    assert evaluate(cfg, tmp_path / "run")["miou"] == m["miou"]
    llff_scene(root / "broken", NAMES[:4])
    from bench.runners.rundir import RunExists

    with pytest.raises(RunExists):
        evaluate(cfg, tmp_path / "run")


def test_generic_photographed_views_path_order_and_per_view_split(tmp_path):
    """Views with a photograph vs pose-and-mask-only views: both are scored and told apart,
    with the angle to the nearest photograph; `order=path` starts the video at the prompt."""
    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    _masks(tmp_path / "cap" / "masks", cams, scene, NAMES)
    for n in NAMES[3:]:  # only the first three views were photographed
        (tmp_path / "cap" / "images_4" / f"{n}.JPG").unlink()
    ds = PosedMasksDataset(tmp_path / "cap", mask_dir="masks", reference=NAMES[4], order="path")
    task = ds.load_scene("cap")
    assert task.meta["photographs"] == NAMES[:3]
    assert task.trajectory[0].name == NAMES[4] and task.prompt.frame == 0
    assert sorted(c.name for c in task.trajectory) == NAMES
    report, _ = run_scene(task, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False))
    rows = {r["view"]: r for r in report.views}
    assert [rows[n]["photographed"] for n in NAMES] == [True] * 3 + [False] * 3
    assert all(rows[n]["photo_angle_deg"] == 0.0 for n in NAMES[:3])
    assert all(rows[n]["photo_angle_deg"] > 0.0 for n in NAMES[3:])
    split = report.extra["by_view_group"]
    assert split["coarse_photographed_views"] == 3 and split["coarse_mask_only_views"] == 3
    with pytest.raises(DatasetError, match="order"):
        PosedMasksDataset(tmp_path / "cap", order="random")
    dense = PosedMasksDataset(tmp_path / "cap", mask_dir="masks", reference=NAMES[4], inbetween=2)
    task = dense.load_scene("cap")
    names = [c.name for c in task.trajectory]
    assert len(names) == 6 + 5 * 2 and names[:4] == [
        NAMES[0],
        f"{NAMES[0]}+1",
        f"{NAMES[0]}+2",
        NAMES[1],
    ]
    assert names[task.prompt.frame] == NAMES[4] and task.trajectory_gt is None
    assert [v.name for v in task.eval_views] == NAMES  # only the real views are scored


def test_every_nth_view_is_segmented_and_every_view_scored(tmp_path):
    """`every=4` on six views, the reference the fourth: the video is views 0, 3 and 4 (every
    4th and the reference), the prompt on view 3; all six are scored, and the photographed
    ones are found among all six, not only those of the video."""
    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    _masks(tmp_path / "cap" / "masks", cams, scene, NAMES)
    for n in NAMES[3:]:
        (tmp_path / "cap" / "images_4" / f"{n}.JPG").unlink()
    ds = PosedMasksDataset(tmp_path / "cap", mask_dir="masks", reference=NAMES[3], every=4)
    task = ds.load_scene("cap")
    assert [c.name for c in task.trajectory] == [NAMES[0], NAMES[3], NAMES[4]]
    assert task.trajectory[task.prompt.frame].name == NAMES[3]
    assert [v.name for v in task.eval_views] == NAMES and task.meta["photographs"] == NAMES[:3]
    report, _ = run_scene(task, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False))
    assert report.vote["num_masks"] == 3 and len(report.views) == 6 and report.miou > 0.5
    with pytest.raises(DatasetError, match="every"):
        PosedMasksDataset(tmp_path / "cap", every=0)


def test_scene_renders_on_the_colour_it_was_fitted_on(tmp_path):
    """A fit on white (fit.background) is rendered on white for the segmenter; a scene
    without fit_config.json keeps the pipeline's black."""
    import json

    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    _masks(tmp_path / "cap" / "masks", cams, scene, NAMES)
    ds = PosedMasksDataset(tmp_path / "cap", mask_dir="masks")
    settings = PipelineSettings(progress=False)
    black = ds.load_scene("cap")
    assert black.background is None
    report, out = run_scene(black, OracleSegmenter(), VoteConfig(), settings)
    assert "render_background" not in report.extra
    frames_black, key_black = out.frames.value.images, out.frames.key
    config = tmp_path / "cap" / "gaussians" / "fit_config.json"
    config.write_text(json.dumps({"background": [1.0, 1.0, 1.0], "seed": 0}))
    white = ds.load_scene("cap")
    assert white.background == (1.0, 1.0, 1.0)
    report, out = run_scene(white, OracleSegmenter(), VoteConfig(), settings)
    assert report.extra["render_background"] == [1.0, 1.0, 1.0]
    frames_white = out.frames.value.images
    empty = frames_black[0].max(-1) == 0  # nothing rendered there on black
    assert empty.any() and (frames_white[0][empty] == 255).all()
    assert out.frames.key != key_black and report.views  # another frames stage, scored too


def test_fitted_background_reads_the_fit_config_beside_the_scene(tmp_path):
    """The colour beside a point_cloud.ply (fit_config.json of `make scenes`); None where
    there is no such file or it records no colour; a file that is not JSON or a colour that is
    not three numbers in [0, 1] is refused naming the file (not rendered on black silently)."""
    from sagonline.core.errors import SceneFileError
    from sagonline.scene.io import fitted_background

    ply = tmp_path / "point_cloud.ply"
    assert fitted_background(ply) is None
    config = tmp_path / "fit_config.json"
    config.write_text('{"background": [1, 0.5, 0]}')
    assert fitted_background(ply) == (1.0, 0.5, 0.0)
    for silent in ("[1, 2, 3]", '{"seed": 0}', '{"background": null}'):
        config.write_text(silent)
        assert fitted_background(ply) is None, silent
    for broken, words in (
        ('{"background": [1, 1, ', "not JSON"),
        ('{"background": "white"}', "'white' is not three numbers"),
        ('{"background": 1}', "background 1 is not"),
        ('{"background": ["a", 1, 1]}', "not three numbers r, g, b in [0, 1]"),
        ('{"background": [2, 0, 0]}', "in [0, 1]"),
        ('{"background": [NaN, 0, 0]}', "in [0, 1]"),
        ('{"background": [true, 0, 0]}', "in [0, 1]"),
        ('{"background": [1, 1]}', "in [0, 1]"),
    ):
        config.write_text(broken)
        with pytest.raises(SceneFileError) as exc:
            fitted_background(ply)
        assert str(exc.value).startswith(f"{config}: ") and words in str(exc.value), broken


def test_a_broken_fit_config_fails_the_scene_naming_the_file(tmp_path):
    """The adapters say a broken colour as a dataset error of the scene (the run reports the
    scene failed, naming the file), and `sagonline render` in one line."""
    from sagonline.apps.cli import main

    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    _masks(tmp_path / "cap" / "masks", cams, scene, NAMES)
    config = tmp_path / "cap" / "gaussians" / "fit_config.json"
    config.write_text('{"background": [1, 1, 7]}')
    with pytest.raises(DatasetError, match="fit_config.json: background"):
        PosedMasksDataset(tmp_path / "cap", mask_dir="masks").load_scene("cap")
    ply = tmp_path / "cap" / "gaussians" / "point_cloud.ply"
    assert main(["render", str(ply), "--orbit", "4", "--out", str(tmp_path / "v.png")]) == 2
    assert not (tmp_path / "v.png").exists()


def test_a_photograph_lost_since_the_fit_is_refused_not_regrouped(tmp_path):
    """A capture of one's own pins no photograph count; its fit records how many it was made
    from: one fewer now would move a view to the mask-only group without a word."""
    import json

    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    _masks(tmp_path / "cap" / "masks", cams, scene, NAMES)
    ds = PosedMasksDataset(tmp_path / "cap", mask_dir="masks")
    fit = next((tmp_path / "cap").rglob("point_cloud.ply")).parent
    (fit / "fit_metrics.json").write_text(json.dumps({"images": len(NAMES)}))
    assert len(ds.load_scene("cap").meta["photographs"]) == len(NAMES)
    (tmp_path / "cap" / "images_4" / f"{NAMES[2]}.JPG").unlink()
    with pytest.raises(DatasetError, match="its fit .* was made from 6: a missing photograph"):
        ds.load_scene("cap")


def test_a_fit_of_every_second_photograph_has_a_protocol_of_its_own(tmp_path):
    """A capture whose fit recorded fit.train_every=2 (the sparse-photograph protocol) is scored
    under `...-photos1of2@2`; a fit that records nothing, or every photograph, under the plain
    protocol (whose id, and so every cached run, stays as it was)."""
    import json

    llff_scene(tmp_path / "cap", NAMES)
    ds = PosedMasksDataset(tmp_path / "cap", image_dir="images_4", mask_dir="masks")
    assert ds.protocol == "generic/all-views@2"
    config = tmp_path / "cap" / "gaussians" / "fit_config.json"
    config.write_text(json.dumps({"train_every": 1}))
    assert ds.protocol == "generic/all-views@2"
    config.write_text(json.dumps({"train_every": 2}))
    assert ds.protocol == "generic/all-views-photos1of2@2"
    config.write_text("not json")
    assert ds.protocol == "generic/all-views@2"


def test_a_label_map_read_narrow_with_an_id_past_the_names_is_refused(tmp_path):
    """Label maps keep their files' 8 bits; an id past the dataset's label names is still
    named with its file, and the ids in range load as they are."""
    cams, scene = llff_scene(tmp_path / "ids", NAMES[:2])
    for n in NAMES[:2]:
        m = np.zeros((24, 32), np.uint8)
        m[4:10, 4:12] = 1
        write_image(tmp_path / "ids" / "ids" / f"{n}.png", m)
    settings = dict(
        name="ids", mask_dir="ids", label_format="ids", label_names=["bg", "a"], prompt="none"
    )
    task = PosedMasksDataset(tmp_path / "ids", **settings).load_scene("ids")
    assert task.eval_views[0].gt.dtype == np.uint8 and task.eval_views[0].gt[5, 5] == 1
    m[0, 0] = 2
    write_image(tmp_path / "ids" / "ids" / f"{NAMES[1]}.png", m)
    with pytest.raises(DatasetError, match=rf"{NAMES[1]}\.png: label ids outside \[0, 2\)"):
        PosedMasksDataset(tmp_path / "ids", **settings).load_scene("ids")


def test_per_object_masks_past_255_objects_keep_every_id(tmp_path):
    """A view's per-object masks are merged into the narrowest type that holds their ids:
    uint16 once there are 256 objects, so the last object's id is not wrapped."""
    from sagonline.datasets.labels import PerObjectLabels

    view = tmp_path / "masks" / "view0"
    for k in range(256):
        m = np.zeros((4, 4), np.uint8)
        if k in (0, 255):
            m[k // 255, 1] = 255
        write_image(view / f"obj{k:03d}.png", m)
    merged = PerObjectLabels().read(view)
    assert merged.dtype == np.uint16 and merged[0, 1] == 1 and merged[1, 1] == 256
