"""Numbers a reviewer can trust: every defect of the trust issue, reproduced, then fixed.

Stage caches keyed by content, finished runs that nothing rewrites, sweeps that resume,
scoring that honours `ignore` and refuses empty ground truth, inputs checked before any work.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from bench.runners.eval import evaluate
from bench.runners.rundir import RunExists
from sagonline.datasets.base import DatasetError
from sagonline.pipeline import (
    PipelineSettings,
    SceneReport,
    SegmenterRun,
    StageCache,
    record_scores,
    run_scene,
)
from sagonline.pipeline.stages import VOTE
from sagonline.scene.io import write_ply
from sagonline.scene.io.cameras import CameraFileError, load_cameras, write_3dgs_cameras_json
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig
from tests.fixtures import (
    ROOT,
    TINY,
    cfg_with,
    compose_config,
    llff_scene,
    object_mask,
    write_image,
)

NAMES = [f"IMG_{i:04d}" for i in range(5)]
ALL = ("frames", "masks", "vote")


def generic_cfg(root: Path, *overrides):

    return compose_config(
        "eval",
        *["dataset=generic", f"dataset.root={root}", "progress=false", *overrides],
    )


# --- 1. stage caches keyed by the content they consume ---------------------------------------


def _stages(task, cache, segmenter=None, vote=None, seg_key=None):
    report, _ = run_scene(
        task,
        SegmenterRun(segmenter or OracleSegmenter(), seg_key or {}),
        vote or VoteConfig(),
        PipelineSettings(progress=False),
        cache_dir=cache,
    )
    return {s for s, how in report.stages.items() if how == "computed"}


def test_each_input_recomputes_exactly_the_stages_that_depend_on_it(tiny_task, tmp_path):
    base = tiny_task
    assert _stages(base, tmp_path) == set(ALL)
    assert _stages(base, tmp_path) == set()  # nothing changed: everything from the cache

    g = base.gaussians
    moved = dataclasses.replace(g, opacities=g.opacities.clone())
    moved.opacities[0] *= 0.5  # one parameter of one Gaussian: the scene's bytes differ
    assert _stages(dataclasses.replace(base, gaussians=moved), tmp_path) == set(ALL)

    poses = list(base.trajectory)
    w2c = poses[2].world_to_cam.clone()
    w2c[0, 3] += 1e-3
    poses[2] = dataclasses.replace(poses[2], world_to_cam=w2c)
    assert _stages(dataclasses.replace(base, trajectory=poses), tmp_path) == set(ALL)

    smaller = [c.scaled(20, 15) for c in base.trajectory]
    gt_small = [m[::2, ::2].copy() for m in base.trajectory_gt]
    changed = dataclasses.replace(base, trajectory=smaller, trajectory_gt=gt_small)
    assert _stages(changed, tmp_path) == set(ALL)

    fewer = dataclasses.replace(
        base, trajectory=base.trajectory[:4], trajectory_gt=base.trajectory_gt[:4]
    )
    assert _stages(fewer, tmp_path) == set(ALL)

    noisy = OracleSegmenter(flicker=0.5, seed=3)
    key = {"name": "oracle", "flicker": 0.5, "seed": 3}
    assert _stages(base, tmp_path, segmenter=noisy, seg_key=key) == {"masks", "vote"}

    assert _stages(base, tmp_path, vote=VoteConfig(eps=0.1)) == {"vote"}
    assert _stages(base, tmp_path, vote=VoteConfig(delta=4.0)) == {"vote"}


def test_corrupt_cache_entry_is_named_and_recomputed(tiny_task, tmp_path):
    _stages(tiny_task, tmp_path)
    (vote_file,) = tmp_path.glob("vote-*.store")
    vote_file.write_bytes(b"not a torch file")
    with pytest.warns(UserWarning, match=rf"unusable, removed and recomputed: .*{vote_file.name}"):
        assert _stages(tiny_task, tmp_path) == {"vote"}
    assert StageCache(tmp_path).load(VOTE, vote_file.stem.split("-", 1)[1]) is not None


def test_cached_stages_report_no_timing_of_their_own(tiny_task, tmp_path):
    run = lambda: run_scene(  # noqa: E731
        tiny_task,
        OracleSegmenter(),
        VoteConfig(),
        PipelineSettings(progress=False),
        cache_dir=tmp_path,
    )[0]
    first, second = run(), run()
    assert {"render_ms_per_frame", "vote_ms_per_mask", "time_to_first_mask_s"} <= set(first.timings)
    assert second.stages == dict.fromkeys(ALL, "cached")
    assert not {"render_ms_per_frame", "vote_s", "vote_ms_per_mask", "time_to_first_mask_s"} & set(
        second.timings
    )
    assert second.cached_timings["vote_ms_per_mask"] == first.timings["vote_ms_per_mask"]
    assert second.miou == first.miou


@pytest.mark.slow
def test_replaced_scene_file_and_render_size_are_not_served_from_the_cache(tmp_path):
    """The reproduction: a new point_cloud.ply, or another render_max_side, used to bring
    back the old numbers from the shared cache."""
    root = tmp_path / "data"
    cams, sc = llff_scene(root / "cap", NAMES, width=48, height=36)
    for cam, name in zip(cams, NAMES, strict=True):
        mask = (object_mask(sc, cam) > 0).astype(np.uint8) * 255
        write_image(root / "cap" / "masks" / f"{name}.png", mask)
    base = ["record=false", f"cache_dir={tmp_path / 'cache'}"]
    first = evaluate(generic_cfg(root, *base), tmp_path / "a")
    assert first["scenes"][0]["stages"] == dict.fromkeys(ALL, "computed")
    # another scene in the same place: everything recomputes, the digest says so
    _, other = llff_scene(root / "cap", NAMES, width=48, height=36, seed=5)
    second = evaluate(generic_cfg(root, *base), tmp_path / "b")
    assert second["scenes"][0]["stages"] == dict.fromkeys(ALL, "computed")
    assert second["scenes"][0]["inputs"]["scene"] != first["scenes"][0]["inputs"]["scene"]
    smaller = evaluate(
        generic_cfg(root, *base, "dataset.adapter.render_max_side=24"), tmp_path / "c"
    )
    assert smaller["scenes"][0]["stages"] == dict.fromkeys(ALL, "computed")
    # every generic view has a mask: per_view.csv says which of them voted
    rows = pd.read_csv(tmp_path / "c" / "per_view.csv")
    assert rows["voted"].all() and len(rows) == len(NAMES)


def test_changed_view_count_with_a_shared_cache(tmp_path):
    cache = f"cache_dir={tmp_path / 'cache'}"
    evaluate(cfg_with("record=false", "dataset=synthetic_ff", cache), tmp_path / "a")
    m = evaluate(
        cfg_with(
            "record=false",
            "dataset=synthetic_ff",
            cache,
            "dataset.adapter.forward_single.num_train_views=6",
        ),
        tmp_path / "b",
    )
    assert m["scenes"][0]["vote"]["num_masks"] == 6


# --- 2-3. finished runs that nothing rewrites; sweeps that resume -----------------------------


def _bench_eval(*args, cwd=ROOT, **kw):
    cmd = [sys.executable, "-m", "bench.runners.eval", *args, "progress=false", *TINY]
    return subprocess.Popen(
        cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw
    )


def _snapshot(run_dir: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(run_dir)): p.read_bytes()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file() and "cache" not in p.parts
    }


@pytest.mark.slow
def test_killed_sweep_resumes_and_finished_jobs_stay_byte_identical(tmp_path):
    sweep = tmp_path / "sweep"
    args = [
        "--multirun",
        "consensus.eps=0.01,0.1,0.5",
        "dataset=synthetic_ff",
        "record=false",
        f"hydra.sweep.dir={sweep}",
    ]
    proc = _bench_eval(*args)
    while not (sweep / "1" / "metrics.json").exists():  # bounded by the sweep itself
        assert proc.poll() is None, proc.stdout.read()
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(300)
    assert not (sweep / "2" / "metrics.json").exists()
    before = {j: _snapshot(sweep / j) for j in ("0", "1")}
    sweep_file = (sweep / "multirun.yaml").read_bytes()

    out, _ = _bench_eval(*args).communicate(timeout=300)
    assert out.count("already holds this run") == 2, out
    assert (sweep / "2" / "metrics.json").is_file()
    assert {j: _snapshot(sweep / j) for j in ("0", "1")} == before
    assert (sweep / "multirun.yaml").read_bytes() == sweep_file
    # a sweep with other values into the same folder is refused and changes nothing
    other = _bench_eval(*[a.replace("0.01,0.1,0.5", "0.2,0.3") for a in args])
    out, _ = other.communicate(timeout=300)
    assert other.returncode == 2 and "other overrides" in out
    assert {j: _snapshot(sweep / j) for j in ("0", "1")} == before
    assert (sweep / "multirun.yaml").read_bytes() == sweep_file

    from bench.tables.paper import build

    df = build("ablation", sweep, tmp_path / "reports")
    labels = dict(zip(df["eps"], df["overrides"], strict=True))
    for eps, label in labels.items():
        assert f"consensus.eps={eps:g}" in label


@pytest.mark.slow
def test_refused_rerun_leaves_the_finished_run_untouched(tmp_path):
    run = tmp_path / "run"
    proc = _bench_eval("dataset=synthetic_ff", f"hydra.run.dir={run}")
    assert proc.wait(300) == 0
    before = _snapshot(run)
    assert {".hydra/config.yaml", ".hydra/overrides.yaml", "metrics.json", "eval.log"} <= set(
        before
    )
    assert b"summary" in before["eval.log"]
    from sagonline.core.files import _umask

    assert (run / "metrics.json").stat().st_mode & 0o777 == 0o666 & ~_umask()
    metrics = json.loads(before["metrics.json"])
    assert metrics["status"] == "complete" and metrics["git"]["commit"]
    assert "dataset=synthetic_ff" in metrics["overrides"]
    refused = _bench_eval("dataset=synthetic_ff", "consensus.eps=0.1", f"hydra.run.dir={run}")
    out, _ = refused.communicate(timeout=300)
    assert refused.returncode == 2
    assert "consensus.eps: 0.01 -> 0.1" in out and "Nothing was changed" in out
    assert _snapshot(run) == before


def test_interrupt_keeps_a_recording_of_what_was_done(tmp_path, monkeypatch):
    import bench.runners.eval
    from sagonline.vote.consensus import VoteAccumulator

    add_view, votes = VoteAccumulator.add_view, []

    def stop(self, *args, **kwargs):  # the third view's vote is interrupted
        votes.append(1)
        if len(votes) == 3:
            raise KeyboardInterrupt
        return add_view(self, *args, **kwargs)

    monkeypatch.setattr(VoteAccumulator, "add_view", stop)
    with pytest.raises(KeyboardInterrupt):
        bench.runners.eval.evaluate(cfg_with("dataset=synthetic_ff"), tmp_path)
    assert not (tmp_path / "metrics.json").exists()
    # the frames and masks rendered before the interrupt are in the recording
    assert (tmp_path / "recording.rrd").stat().st_size > 20_000


# --- 5-6. scoring ------------------------------------------------------------------------------


def test_ignore_label_reaches_scoring(tiny_task):
    view = tiny_task.eval_views[0]
    gt = view.gt.copy()
    gt[0, 0] = 255
    task = dataclasses.replace(
        tiny_task, eval_views=[dataclasses.replace(view, gt=gt)], ignore_label=255
    )
    report = SceneReport(scene="s")
    miou, _ = record_scores(task, [view.gt], "pred_to_gt", report, "coarse")
    assert miou == pytest.approx(1.0)  # was 0.5: the void pixel counted as a missed label


def test_empty_ground_truth_fails_the_scene_with_a_hint(tmp_path):
    root = tmp_path / "data"
    llff_scene(root / "cap", NAMES)
    for name in NAMES:
        write_image(root / "cap" / "masks" / f"{name}.png", np.zeros((24, 32), np.uint8))
    cfg = generic_cfg(root, "record=false")
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg, tmp_path / "run")
    assert exc.value.code == 1
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["status"] == "failed"
    assert "mask_threshold=0" in saved["scenes"][0]["error"]
    # a failed run does not block its rerun once the data is fixed
    _, sc = llff_scene(root / "cap", NAMES)
    for cam, name in zip(load_cameras(root / "cap"), NAMES, strict=True):
        mask = (object_mask(sc, cam) > 0).astype(np.uint8) * 255
        write_image(root / "cap" / "masks" / f"{name}.png", mask)
    assert evaluate(cfg, tmp_path / "run")["status"] == "complete"


def test_zero_one_masks_read_as_binary_are_refused(tmp_path):
    from sagonline.datasets.common import load_mask

    path = tmp_path / "m.png"
    write_image(path, (np.arange(48).reshape(6, 8) % 2).astype(np.uint8))
    with pytest.raises(DatasetError, match=r"m\.png.*mask_threshold=0"):
        load_mask(path, threshold=127)
    assert load_mask(path, threshold=0).sum() == 24


# --- 4. make scenes never replaces a scene it did not write -----------------------------------


def test_make_scenes_leaves_a_users_scene_alone(tmp_path, capsys):
    from bench.runners.scenes import fit_scene
    from sagonline.datasets.generic import PosedMasksDataset

    cams, sc = llff_scene(tmp_path / "cap", NAMES)  # the user's own trained scene
    ply = tmp_path / "cap" / "gaussians" / "point_cloud.ply"
    before = ply.read_bytes()
    for cam, name in zip(cams, NAMES, strict=True):
        mask = (object_mask(sc, cam) > 0).astype(np.uint8) * 255
        write_image(tmp_path / "cap" / "masks" / f"{name}.png", mask)

    cfg = compose_config("scenes", *["dataset=generic", "progress=false"])
    adapter = PosedMasksDataset(tmp_path / "cap", mask_dir="masks")
    assert fit_scene(cfg, adapter, "cap") == {"scene": "cap", "skipped": True}
    assert "did not write" in capsys.readouterr().err
    assert ply.read_bytes() == before


# --- 7-8. the command line and camera files ----------------------------------------------------


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


def _nerf(path: Path, **changes) -> Path:
    frame = {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"camera_angle_x": 0.8, "w": 32, "h": 24, "frames": [frame]}
    for key, value in changes.items():
        (frame if key == "transform_matrix" else meta)[key] = value
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"transform_matrix": np.full((4, 4), np.nan).tolist()}, "NaN/Inf"),
        ({"camera_angle_x": 0.0}, "not a pinhole field of view"),
        ({"camera_angle_x": float(np.pi)}, "not a pinhole field of view"),
        ({"transform_matrix": np.zeros((4, 4)).tolist()}, "frame 'a' has a singular pose"),
        ({"transform_matrix": (2 * np.eye(4)).tolist()}, "not a rotation"),
        ({"transform_matrix": np.eye(3).tolist()}, "is 3x3; expected 4x4 or 3x4"),
        ({"camera_angle_x": "wide"}, ""),
        ({"w": 0}, "not positive"),
        ({"w": -32}, "not positive"),
    ],
)
def test_bad_cameras_name_the_file(tmp_path, change, message):
    path = _nerf(tmp_path / "transforms.json", **change)
    with pytest.raises(CameraFileError, match=rf"transforms\.json: .*{message}"):
        load_cameras(path)


def test_nerf_file_under_another_name_loads(tmp_path):
    cams = load_cameras(_nerf(tmp_path / "poses_for_my_scene.json"))
    assert len(cams) == 1 and cams[0].width == 32
    assert torch.isfinite(cams[0].K).all()


# --- 9-10. checks before any work -----------------------------------------------------------


def _fails_before_rendering(tmp_path, *overrides) -> str:
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff", *overrides), run)
    assert exc.value.code == 2
    assert not (run / "cache").exists()  # nothing was rendered
    return str(exc.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA message")
def test_cuda_without_cuda_fails_before_rendering(tmp_path, capsys):
    _fails_before_rendering(tmp_path, "device=cuda")
    assert "device=cuda: CUDA is not available" in capsys.readouterr().err


def test_mistyped_vote_setting_names_the_key():
    from hydra.errors import ConfigCompositionException

    for override, key in (("consensus.eps=abc", "consensus.eps"), ("consensus.epz=0.1", "epz")):
        with pytest.raises(ConfigCompositionException) as exc:  # at composition, before any work
            cfg_with("dataset=synthetic_ff", override)
        assert key in f"{exc.value} {exc.value.__cause__}", override


def test_unreadable_sam2_checkpoint_fails_before_rendering(tmp_path, capsys):
    pytest.importorskip("sam2")
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()  # importing sam2 initialises Hydra globally
    bad = tmp_path / "sam2.pt"
    bad.write_bytes(os.urandom(4096))
    _fails_before_rendering(tmp_path, "segmenter=sam2", f"segmenter.checkpoint={bad}")
    err = capsys.readouterr().err
    assert f"segmenter.checkpoint={bad}" in err and "not a readable PyTorch checkpoint" in err


def test_unreadable_yolo_weights_fail_before_rendering(tmp_path, capsys):
    pytest.importorskip("ultralytics")
    bad = tmp_path / "yolo.pt"
    bad.write_bytes(os.urandom(4096))
    _fails_before_rendering(tmp_path, "segmenter=yolo", f"segmenter.weights={bad}")
    assert f"segmenter.weights={bad}" in capsys.readouterr().err


def test_weights_digest_joins_the_masks_key(tmp_path):
    from sagonline.core.provenance import digest_file

    f = tmp_path / "w.pt"
    f.write_bytes(b"a" * 10)
    first = digest_file(f)
    time.sleep(0.01)
    f.write_bytes(b"b" * 10)  # same size, new mtime: read again
    assert digest_file(f) != first


def test_refusal_is_a_run_exists(tmp_path):
    evaluate(cfg_with("record=false", "dataset=synthetic_ff"), tmp_path)
    with pytest.raises(RunExists):
        evaluate(cfg_with("record=false", "dataset=synthetic_ff", "seed=1"), tmp_path)


def _digest_many(args) -> None:
    from sagonline.core.provenance import digest_file

    folder, start = args
    for i in range(start, start + 20):
        digest_file(Path(folder) / f"f{i}.bin")


@pytest.mark.slow
def test_the_digest_memo_keeps_every_process_entries(tmp_path, monkeypatch):
    """Two processes digesting at once: the memo file holds the entries of both (it was
    rewritten without a lock, one process's entries lost)."""
    import json
    import multiprocessing as mp

    memo = tmp_path / "memo.json"
    monkeypatch.setenv("SAGONLINE_DIGEST_CACHE", str(memo))
    for i in range(40):
        (tmp_path / f"f{i}.bin").write_bytes(os.urandom(64))
    with mp.get_context("spawn").Pool(2) as pool:
        pool.map(_digest_many, [(str(tmp_path), 0), (str(tmp_path), 20)])
    assert len(json.loads(memo.read_text())) == 40


def test_a_metrics_json_that_is_no_object_is_named(tmp_path, capsys):
    """A finished-looking run folder whose metrics.json holds a list: one line naming the file,
    exit 2 (it was a traceback)."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text("[1, 2]")
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff"), run)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "metrics.json: holds a list, not a run's metrics" in err and err.count("\n") == 1


def test_ground_truth_digest_is_remembered_only_while_nothing_can_change_it():
    """Read-only ground truth is hashed once per process, with the digest its bytes give;
    an array that can be written is hashed every time, so a change is always seen."""
    from sagonline.core.provenance import digest_arrays
    from sagonline.datasets.base import read_only

    frozen = [read_only(np.full((600, 600), k, np.int64)) for k in range(2)]
    copies = [a.copy() for a in frozen]
    assert digest_arrays(frozen) == digest_arrays(frozen) == digest_arrays(copies)
    writable = [np.zeros((600, 600), np.int64)]
    before = digest_arrays(writable)
    writable[0][0, 0] = 1
    assert digest_arrays(writable) != before
    with pytest.raises(ValueError, match="read-only"):
        frozen[0][0, 0] = 7


def test_a_setting_added_since_a_run_at_its_old_behaviour_keeps_the_run_the_same():
    """A finished run recorded before consensus.body, consensus.weighting and label_render.size
    existed compares equal to this config with the rule off, the paper's count and labels
    rendered at the view's size, and differs from it with any of them changed."""
    from bench.runners.rundir import ADDED_SETTINGS, comparable_config, finished_config

    now = {
        "consensus": {"method": "rgc", "body": False, "weighting": "count"},
        "label_render": {"min_weight": 0.2, "size": "render"},
        "dataset": {"name": "x"},
    }
    before = {
        "consensus": {"method": "rgc"},
        "label_render": {"min_weight": 0.2},
        "dataset": {"name": "x"},
    }
    assert {"consensus.body", "consensus.weighting", "label_render.size"} <= set(ADDED_SETTINGS)
    assert finished_config(before) == comparable_config(now)
    now["consensus"]["body"] = True
    assert finished_config(before) != comparable_config(now)
    now["consensus"].update(body=False, weighting="blend")
    assert finished_config(before) != comparable_config(now)
    now["consensus"]["weighting"] = "count"
    now["label_render"]["size"] = "truth"
    assert finished_config(before) != comparable_config(now)
