"""Nothing executes, nothing is silently wrong, nothing is lost: one test per defect of the
bad-inputs issue (code that runs on load, damaged caches, a user's scene lost, outputs over
inputs, tracebacks, nonsense accepted), and seeded mutations of every file format the harness
reads, each of which must give a clear error naming the file or a valid load."""

from __future__ import annotations

import json
import os
import pickle
import random
import re
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import torch

from bench.runners.eval import evaluate
from sagonline.datasets.base import DatasetError
from sagonline.datasets.common import load_mask
from sagonline.pipeline import PipelineSettings, run_scene
from sagonline.scene.io import SceneFileError, read_scene, write_ply
from sagonline.scene.io.cameras import CameraFileError, load_cameras, write_3dgs_cameras_json
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig
from tests.fixtures import (
    ROOT,
    cfg_with,
    compose_config,
    llff_scene,
    object_mask,
    random_gaussians,
    write_image,
)

NAMES = [f"IMG_{i:04d}" for i in range(5)]


class Planted:
    """A pickled object that writes a file when unpickled: what an attacker leaves in a cache."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "code ran"))


def plant(path: Path, marker: Path, how: str = "torch") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    value = {"model": Planted(marker), "state": Planted(marker)}
    if how == "torch":
        torch.save(value, path)
    else:
        path.write_bytes(pickle.dumps(value))
    return path


def _stage_one(task, cache):
    report, stage_one = run_scene(
        task, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False), cache_dir=cache
    )
    return report, stage_one.vote.value


# --- 1. code runs on load ---------------------------------------------------------------------


def test_pickled_cache_entry_never_runs(tiny_task, tmp_path):
    _stage_one(tiny_task, tmp_path)
    marker = tmp_path / "ran.txt"
    for entry in tmp_path.glob("*.store"):
        plant(entry, marker)  # a pickle under the name of each valid entry
    with pytest.warns(UserWarning, match="not a file the harness wrote") as caught:
        report, _ = _stage_one(tiny_task, tmp_path)
    assert not marker.exists()
    assert report.stages == {"frames": "computed", "masks": "computed", "vote": "computed"}
    assert len([w for w in caught if "removed and recomputed" in str(w.message)]) == 3


def test_pickled_fit_and_student_checkpoints_never_run(tmp_path):
    from sagonline.fitting import FitConfig, SceneFitter
    from sagonline.refine import RefineConfig, RefinementTrainer

    marker = tmp_path / "ran.txt"
    fit_ckpt = plant(tmp_path / "fit_checkpoint.store", marker)
    cams, sc = llff_scene(tmp_path / "cap", NAMES, with_scene=False)
    imgs = [torch.rand(c.height, c.width, 3) for c in cams]
    fitter = SceneFitter(FitConfig(iterations=2, init_points=200, max_gaussians=400), cams, imgs)
    with pytest.warns(UserWarning, match="fit checkpoint unusable.*fit_checkpoint.store"):
        assert not fitter.resume(fit_ckpt)
    assert not fit_ckpt.exists() and not marker.exists()

    student = plant(tmp_path / "refine.store", marker, how="raw")
    frames = [np.zeros((32, 32, 3), np.uint8)] * 2
    masks = [np.zeros((32, 32), np.int64)] * 2
    with pytest.warns(UserWarning, match="student checkpoint unusable.*refine.store"):
        trainer = RefinementTrainer(RefineConfig(max_steps=2), 2, frames, masks, masks, student)
    assert trainer.step == 0 and not student.exists() and not marker.exists()


def test_pickled_yolo_weights_are_refused_by_name(tmp_path):
    pytest.importorskip("ultralytics")
    from sagonline.scene.io.checkpoints import UntrustedCheckpoint
    from sagonline.segment.yolo import YOLOSegmenter

    marker = tmp_path / "ran.txt"
    weights = plant(tmp_path / "yolo.pt", marker)
    with pytest.raises(
        UntrustedCheckpoint, match=r"segmenter\.weights=.*yolo\.pt.*trust_checkpoint"
    ):
        YOLOSegmenter(weights=str(weights)).check()
    assert not marker.exists()


def test_a_real_yolo_checkpoint_loads_without_trust(tmp_path):
    pytest.importorskip("ultralytics")
    from sagonline.segment.yolo import YOLOSegmenter

    model = YOLOSegmenter(model_yaml="yolo11n-seg.yaml").load_model()  # random weights
    model.save(tmp_path / "random.pt")  # a full ultralytics checkpoint (pickled model)
    loaded = YOLOSegmenter(weights=str(tmp_path / "random.pt")).load_model()
    assert type(loaded.model).__name__ == "SegmentationModel"


@pytest.mark.parametrize("option", ["sam3", "pretrained"])
def test_pickled_user_checkpoints_are_refused_by_name(tmp_path, option):
    from sagonline.refine.network import ResNetEncoder, load_imagenet_weights
    from sagonline.scene.io.checkpoints import UntrustedCheckpoint
    from sagonline.segment.sam3_text import SAM3TextSegmenter

    marker = tmp_path / "ran.txt"
    path = plant(tmp_path / "w.pt", marker)
    with pytest.raises(UntrustedCheckpoint, match="arbitrary unpickling") as exc:
        if option == "sam3":
            SAM3TextSegmenter(checkpoint=str(path)).check()
        else:
            load_imagenet_weights(ResNetEncoder("resnet18"), path)
    assert str(path) in str(exc.value) and not marker.exists()


# --- 2. a damaged cache entry is never read as numbers ------------------------------------------


def test_changed_bytes_inside_a_cache_entry_are_recomputed(tiny_task, tmp_path):
    clean, clean_vote = _stage_one(tiny_task, tmp_path)
    for entry in tmp_path.glob("*.store"):
        data = bytearray(entry.read_bytes())
        middle = len(data) // 2
        data[middle : middle + 4] = bytes(b ^ 0x5A for b in data[middle : middle + 4])
        entry.write_bytes(data)  # the container stays well formed; its digest does not
    with pytest.warns(UserWarning, match="do not match their recorded digest"):
        again, vote = _stage_one(tiny_task, tmp_path)
    assert set(again.stages.values()) == {"computed"}
    assert again.miou == clean.miou and torch.equal(vote.labels, clean_vote.labels)


def test_store_refuses_damage_before_decoding(tmp_path):
    from sagonline.core import store

    value = {"a": torch.arange(10), (1, 2): [np.ones(3), None, float("inf")], "s": {3, 1}}
    path = store.save(tmp_path / "x.store", value)
    back = store.load(path)
    assert torch.equal(back["a"], value["a"]) and back[(1, 2)][2] == float("inf")
    assert back["s"] == {1, 3}
    raw = path.read_bytes()
    for damaged in (raw[:-1], raw[:20], raw[:60] + b"\0" + raw[61:], b"PK" + raw[2:]):
        path.write_bytes(damaged)
        with pytest.raises(store.StoreError, match=re.escape(str(path))):
            store.load(path)


# --- 3. the user's scene is never lost ----------------------------------------------------------


def _scenes_cfg(*overrides):

    return compose_config(
        "scenes",
        *[
            "dataset=generic",
            "progress=false",
            "fit.iterations=2",
            "fit.init_points=300",
            "fit.init=random",
            "fit.view_clearance=0",
            *overrides,
        ],
    )


def test_interrupted_overwrite_keeps_the_users_scene(tmp_path, capsys):
    from bench.runners.scenes import fit_scene
    from sagonline.core import store
    from sagonline.datasets.generic import PosedMasksDataset

    cams, sc = llff_scene(tmp_path / "cap", NAMES)
    for cam, name in zip(cams, NAMES, strict=True):
        write_image(tmp_path / "cap" / "masks" / f"{name}.png", object_mask(sc, cam) * 255)
    out = tmp_path / "cap" / "gaussians"
    users = (out / "point_cloud.ply").read_bytes()
    # what an overwrite=true fit killed after its first checkpoint leaves behind
    store.save(out / "fit_checkpoint.store", {"config": {}, "step": 1})
    adapter = PosedMasksDataset(tmp_path / "cap", mask_dir="masks")
    assert fit_scene(_scenes_cfg(), adapter, "cap")["skipped"]  # without overwrite: refused
    assert "did not write" in capsys.readouterr().err
    assert (out / "point_cloud.ply").read_bytes() == users
    fit_scene(_scenes_cfg("overwrite=true"), adapter, "cap")
    (backup,) = out.glob("point_cloud.ply.bak-*")
    assert backup.read_bytes() == users
    assert fit_scene(_scenes_cfg(), adapter, "cap")["skipped"]  # ours now: already fitted
    assert "already fitted" in capsys.readouterr().out


# --- 4-5. the command line: outputs never over inputs, sizes and colours checked ---------------


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
@pytest.mark.slow
def test_render_sizes_and_backgrounds_are_checked(tmp_path, scene_files, args, message):
    ply, cams = scene_files
    r = _cli("render", str(ply), "--cameras", str(cams), "--out", str(tmp_path / "v.png"), *args)
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    assert message in r.stderr and not (tmp_path / "v.png").exists()


def test_pixel_ceiling_names_itself():
    from sagonline.scene.cameras import MAX_PIXELS, intrinsics, make_camera

    with pytest.raises(ValueError, match=r"MAX_PIXELS.*SAGONLINE_MAX_PIXELS"):
        make_camera(intrinsics(10, 10, 5, 5), np.eye(4), 100_000, MAX_PIXELS // 100_000 + 1)


def _generic_capture(root: Path) -> Path:
    cams, sc = llff_scene(root, NAMES)
    for cam, name in zip(cams, NAMES, strict=True):
        write_image(root / "masks" / f"{name}.png", object_mask(sc, cam) * 255)
    return root


def _eval_generic(root: Path, run: Path, *overrides):
    cfg = compose_config(
        "eval",
        *[
            "dataset=generic",
            f"dataset.root={root}",
            "progress=false",
            "record=false",
            "dataset.adapter.image_dir=null",
            *overrides,
        ],
    )
    return evaluate(cfg, run)


def test_random_bytes_as_poses_bounds_name_the_file(tmp_path, capsys):
    root = _generic_capture(tmp_path / "cap")
    (root / "poses_bounds.npy").write_bytes(os.urandom(2000))
    with pytest.raises(SystemExit):
        _eval_generic(tmp_path, tmp_path / "run")
    err = capsys.readouterr().err
    assert "poses_bounds.npy" in err and "not a readable .npy" in err


def test_read_only_run_folder_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff"), blocker / "run")  # cannot be created
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "cannot be written" in err and str(blocker) in err


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("consensus.num_masks=-3", "consensus.num_masks=-3: must be > 0"),
        ("consensus.margin=2", "consensus.margin=2.0: must be a share gap in [0, 1)"),
        ("consensus.eps=1.5", "consensus.eps=1.5"),
        ("refine=student refine.max_steps=-1", "refine.max_steps=-1: must be >= 1"),
        ("refine=student refine.time_budget_s=-1", "refine.time_budget_s=-1.0"),
        ("refine=student refine.pretrained=/nonexistent.pt", "refine.pretrained=/nonexistent.pt"),
    ],
)
@pytest.mark.slow
def test_settings_out_of_bounds_stop_before_any_work(tmp_path, capsys, override, message):
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff", *override.split()), run)
    assert exc.value.code == 2 and not (run / "cache").exists()
    assert message in capsys.readouterr().err


def test_report_skips_a_bad_metrics_file_and_names_it(tmp_path, capsys):
    from bench.tables.report import main

    evaluate(cfg_with("dataset=synthetic_ff", "record=false"), tmp_path / "runs" / "good")
    for name, text in (("truncated", '{"dataset": "x", "sce'), ("empty", "{}")):
        (tmp_path / "runs" / name).mkdir()
        (tmp_path / "runs" / name / "metrics.json").write_text(text)
    main([str(tmp_path / "runs"), "--out", str(tmp_path / "reports")])
    err = capsys.readouterr().err
    assert "truncated/metrics.json: unreadable" in err and "empty/metrics.json: lacks" in err
    rows = (tmp_path / "reports" / "runs.csv").read_text().strip().splitlines()
    assert len(rows) == 2  # header + the good run, no row of blanks


# --- 6-7. nonsense is refused; the NaN hint can be followed ------------------------------------


def test_overflowing_log_scale_is_refused_like_nan(tmp_path):
    g = random_gaussians(20)
    path = write_ply(tmp_path / "s.ply", g)
    text = path.read_bytes()
    header_end = text.index(b"end_header\n") + len(b"end_header\n")
    data = np.frombuffer(text[header_end:], dtype=np.float32).copy().reshape(20, -1)
    props = [ln.split()[-1] for ln in text[:header_end].decode().splitlines() if "property" in ln]
    data[7, props.index("scale_1")] = 100.0  # finite in the file, inf after exp
    path.write_bytes(text[:header_end] + data.tobytes())
    with pytest.raises(SceneFileError, match=r"'scale_1'.*overflow.*row 7.*drop_nonfinite=true"):
        read_scene(path)
    with pytest.warns(UserWarning, match="dropped 1 of 20"):
        assert len(read_scene(path, drop_nonfinite=True)) == 19


def test_nan_hint_is_an_eval_setting(tmp_path, capsys):
    root = _generic_capture(tmp_path / "cap")
    ply = root / "gaussians" / "point_cloud.ply"
    g = read_scene(ply)
    g.means[3, 0] = float("nan")
    write_ply(ply, g)
    with pytest.raises(SystemExit):
        _eval_generic(tmp_path, tmp_path / "run")
    assert "dataset.adapter.drop_nonfinite=true" in capsys.readouterr().err
    metrics = _eval_generic(tmp_path, tmp_path / "run2", "dataset.adapter.drop_nonfinite=true")
    assert metrics["scenes_scored"] == 1


def test_singular_llff_pose_names_the_frame(tmp_path):
    llff_scene(tmp_path, NAMES, with_scene=False)
    arr = np.load(tmp_path / "poses_bounds.npy")
    arr[2, :15] = 0.0
    arr[2, [4, 9, 14]] = [24, 32, 30]  # keep h, w, f
    np.save(tmp_path / "poses_bounds.npy", arr)
    with pytest.raises(CameraFileError, match="frame '00002' has a singular pose"):
        load_cameras(tmp_path / "poses_bounds.npy")


# --- 8. reading a scene needs little more memory than the scene itself ------------------------


def test_reading_a_ply_peaks_below_one_and_a_half_times_its_size(tmp_path, monkeypatch):
    from sagonline.scene.io import ply_rows

    path = write_ply(tmp_path / "big.ply", random_gaussians(40_000, sh_degree=3))
    monkeypatch.setattr(ply_rows, "BLOCK_ROWS", 2048)
    tracemalloc.start()
    g = read_scene(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(g) == 40_000
    assert peak <= 1.5 * path.stat().st_size, peak / path.stat().st_size


# --- mutations: every format, truncated, flipped, edited -------------------------------------


def mutate(data: bytes, rng: random.Random, header_end: int) -> bytes:
    """Truncation, byte flips (anywhere or in the header), or an edited number in the header."""
    kind = rng.choice(["truncate", "flip", "flip_header", "edit_number", "drop_line"])
    if kind == "truncate":
        return data[: rng.randrange(len(data))]
    out = bytearray(data)
    if kind in ("flip", "flip_header"):
        end = header_end if kind == "flip_header" else len(out)
        for _ in range(rng.randint(1, 8)):
            out[rng.randrange(max(end, 1))] = rng.randrange(256)
        return bytes(out)
    head = data[:header_end].decode("latin-1")
    if kind == "edit_number":
        numbers = list(re.finditer(r"\d+", head))
        if numbers:
            m = rng.choice(numbers)
            new = str(rng.choice([0, 1, 7, 10**6, 10**12, 2**63, int(m.group()) * 3]))
            head = head[: m.start()] + new + head[m.end() :]
    else:
        lines = head.split("\n")
        if len(lines) > 2:
            del lines[rng.randrange(1, len(lines) - 1)]
        head = "\n".join(lines)
    return head.encode("latin-1") + data[header_end:]


def _valid_scene(g) -> bool:
    """What a scene reader returns for good input: finite activated Gaussians."""
    return (
        len(g) > 0
        and bool(torch.isfinite(g.means).all() and torch.isfinite(g.scales).all())
        and bool(((g.opacities >= 0) & (g.opacities <= 1)).all() and (g.scales > 0).all())
        and bool(((g.quats.norm(dim=1) - 1).abs() < 1e-3).all())
    )


def _valid_cameras(cams) -> bool:
    return len(cams) > 0 and all(c.width > 0 and c.height > 0 for c in cams)


def _valid_mask(m) -> bool:
    return m.ndim == 2 and m.dtype == np.int64 and set(np.unique(m).tolist()) <= {0, 1}


def _ply_case(tmp: Path):
    path = write_ply(tmp / "s.ply", random_gaussians(60, kind="2dgs", sh_degree=1))
    return path, path.read_bytes().index(b"end_header") + 11, read_scene, SceneFileError


def _splat_case(tmp: Path):
    rng = np.random.default_rng(0)
    rows = np.zeros(40, [("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)])
    rows["p"], rows["s"] = rng.normal(size=(40, 3)), rng.uniform(0.01, 0.1, (40, 3))
    rows["c"], rows["r"] = 200, [255, 128, 128, 128]
    path = tmp / "s.splat"
    path.write_bytes(rows.tobytes())
    return path, 0, read_scene, SceneFileError


def _transforms_case(tmp: Path):
    frames = [
        {"file_path": f"./v{i}.png", "transform_matrix": np.eye(4).tolist()} for i in range(3)
    ]
    path = tmp / "transforms.json"
    path.write_text(json.dumps({"camera_angle_x": 0.8, "w": 32, "h": 24, "frames": frames}))
    return path, len(path.read_bytes()), load_cameras, CameraFileError


def _poses_case(tmp: Path):
    llff_scene(tmp, NAMES, with_scene=False)
    path = tmp / "poses_bounds.npy"
    return path, path.read_bytes().index(b"\n") + 1, load_cameras, CameraFileError


def _mask_case(tmp: Path):
    path = tmp / "m.png"
    mask = np.zeros((24, 32), np.uint8)
    mask[5:15, 8:20] = 255
    write_image(path, mask)
    return path, 33, load_mask, DatasetError


VALID = {
    "_ply_case": _valid_scene,
    "_splat_case": _valid_scene,
    "_transforms_case": _valid_cameras,
    "_poses_case": _valid_cameras,
    "_mask_case": _valid_mask,
}


@pytest.mark.parametrize(
    "case", [_ply_case, _splat_case, _transforms_case, _poses_case, _mask_case]
)
def test_mutated_files_give_a_clear_error_or_a_valid_load(tmp_path, case):
    path, header_end, load, error = case(tmp_path)
    original = path.read_bytes()
    rng = random.Random(f"{case.__name__}-0")
    outcomes = {"error": 0, "loaded": 0}
    valid = VALID[case.__name__]
    for trial in range(60):
        path.write_bytes(mutate(original, rng, header_end))
        try:
            result = load(path)
        except error as exc:
            assert str(path) in str(exc) or path.name in str(exc), (trial, exc)
            outcomes["error"] += 1
            continue
        assert valid(result), trial  # a valid load: what the reader returns for good input
        outcomes["loaded"] += 1
    assert outcomes["error"] > 0, outcomes
