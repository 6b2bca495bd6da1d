"""The stage cache: entries keyed by their inputs' content, checked before use and never unpickled;
damaged, foreign or lying entries recomputed; an unusable cache folder said once while the run
goes on."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import time

import numpy as np
import pandas as pd
import pytest
import torch

from bench.runners.eval import evaluate
from sagonline.apps.cli import main
from sagonline.pipeline import (
    PipelineSettings,
    SegmenterRun,
    StageCache,
    run_scene,
)
from sagonline.pipeline.stages import VOTE
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig
from tests.fixtures import (
    cfg_with,
    llff_scene,
    object_mask,
    write_image,
)
from tests.refusals import (
    NAMES,
    generic_cfg,
    plant,
)


def _stage_one(task, cache):
    report, stage_one = run_scene(
        task, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False), cache_dir=cache
    )
    return report, stage_one.vote.value


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
    rest = raw[8 + 32 :]  # a file of the first format: BLAKE2b-256 of the same bytes
    first = b"SAGOST01" + hashlib.blake2b(rest, digest_size=32).digest() + rest
    for damaged in (raw[:-1], raw[:20], raw[:60] + b"\0" + raw[61:], b"PK" + raw[2:]):
        path.write_bytes(damaged)
        with pytest.raises(store.StoreError, match=re.escape(str(path))):
            store.load(path)
    path.write_bytes(first)  # still loads, and its damage is still found
    assert store.load(path)["s"] == {1, 3}
    for damaged in (first[:60] + b"\0" + first[61:], b"SAGOST01" + raw[8:]):
        path.write_bytes(damaged)
        with pytest.raises(store.StoreError, match="do not match their recorded digest"):
            store.load(path)


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


@pytest.mark.parametrize("kind", ["file", "loop"])
def test_an_eval_with_an_unusable_cache_dir_finishes(tmp_path, kind):
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


ALL = ("frames", "masks", "vote")


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


def test_weights_digest_joins_the_masks_key(tmp_path):
    from sagonline.core.provenance import digest_file

    f = tmp_path / "w.pt"
    f.write_bytes(b"a" * 10)
    first = digest_file(f)
    time.sleep(0.01)
    f.write_bytes(b"b" * 10)  # same size, new mtime: read again
    assert digest_file(f) != first


def test_a_setting_added_since_a_run_at_its_old_behaviour_keeps_the_run_the_same():
    """A finished run recorded before consensus.body, consensus.weighting, label_render.size,
    the SAM family's segmenter.max_growth, refine.curve_every and refine.ema_span existed
    compares equal to this config with the rule off, the paper's count, labels rendered at the
    view's size, no growth bound, no curve and no weight average, and differs from it with any
    of them changed; a plug-in without the setting (the classical segmenter) is compared
    without it."""
    from bench.runners.rundir import ADDED_SETTINGS, comparable_config, finished_config

    now = {
        "consensus": {"method": "rgc", "body": False, "weighting": "count"},
        "label_render": {"min_weight": 0.2, "size": "render"},
        "segmenter": {"name": "minisam", "max_growth": None},
        "refine": {"seed": 0, "curve_every": 0, "ema_span": 0},
        "dataset": {"name": "x"},
    }
    before = {
        "consensus": {"method": "rgc"},
        "label_render": {"min_weight": 0.2},
        "segmenter": {"name": "minisam"},
        "refine": {"seed": 0},
        "dataset": {"name": "x"},
    }
    assert {"consensus.body", "consensus.weighting", "label_render.size"} <= set(ADDED_SETTINGS)

    def same() -> bool:
        flat = comparable_config(now)
        return finished_config(before, flat) == flat

    assert same()
    now["consensus"]["body"] = True
    assert not same()
    now["consensus"].update(body=False, weighting="blend")
    assert not same()
    now["consensus"]["weighting"] = "count"
    now["label_render"]["size"] = "truth"
    assert not same()
    now["label_render"]["size"] = "render"
    now["segmenter"]["max_growth"] = 3.0
    assert not same()
    now["segmenter"]["max_growth"] = None
    for key, value in (("curve_every", 25), ("ema_span", 60)):
        now["refine"][key] = value
        assert not same()
        now["refine"][key] = 0
    assert same()
    now["segmenter"] = before["segmenter"] = {"name": "classical", "recover": 0.5}
    assert same()


def test_masks_are_cached_narrow_and_an_int64_entry_from_before_still_serves(tiny_task, tmp_path):
    """The masks stage keeps the segmenter's answers at a byte a pixel; an entry written when
    they were int64 is served as it is, with the same vote and the same masks digest."""
    from sagonline.pipeline.stages import MASKS

    settings = PipelineSettings(progress=False)
    report, stage_one = run_scene(
        tiny_task, OracleSegmenter(), VoteConfig(), settings, cache_dir=tmp_path
    )
    narrow = stage_one.masks.value
    assert {m.dtype for m in narrow.masks} == {np.dtype(np.uint8)}
    wide = dataclasses.replace(narrow, masks=[m.astype(np.int64) for m in narrow.masks])
    StageCache(tmp_path).save(MASKS, stage_one.keys["masks"], wide)
    for entry in tmp_path.glob(f"{VOTE.name}-*"):
        entry.unlink()  # the vote is made again, from the int64 masks
    again, served = run_scene(
        tiny_task, OracleSegmenter(), VoteConfig(), settings, cache_dir=tmp_path
    )
    assert again.stages["masks"] == "cached" and again.stages["vote"] == "computed"
    assert {m.dtype for m in served.masks.value.masks} == {np.dtype(np.int64)}
    assert again.inputs["masks"] == report.inputs["masks"]
    assert torch.equal(served.vote.value.histogram, stage_one.vote.value.histogram)
