"""docs/extending.md's three examples, run exactly as the page writes them: a segmenter, a
dataset adapter and a vote rule, each one file registered by itself, then used through the
command line, Hydra's options and both vote kernels."""

from __future__ import annotations

import importlib
import json
import re
import subprocess
import sys

import numpy as np
import pytest

from sagonline.core.plugins import DATASETS, SEGMENTERS, VOTE_RULES
from tests.fixtures import ROOT, compose_config, llff_scene, object_mask, own_scene, write_image

DOC = ROOT / "docs" / "extending.md"


def examples() -> dict[str, str]:
    """file name -> the code block after its `<!-- example: NAME -->` marker."""
    text = DOC.read_text()
    found = re.findall(r"<!-- example: (\S+) -->\n```python\n(.*?)```", text, re.S)
    return dict(found)


@pytest.fixture
def example(tmp_path, monkeypatch):
    """Import one example module from the page (registering its plug-in), and unregister it
    after the test."""
    code = examples()
    monkeypatch.syspath_prepend(str(tmp_path))
    registered = []

    def load(name: str):
        (tmp_path / name).write_text(code[name])
        before = {r: set(r.keys()) for r in (SEGMENTERS, DATASETS, VOTE_RULES)}
        module = importlib.import_module(name.removesuffix(".py"))
        for registry, keys in before.items():
            registered.extend((registry, k) for k in set(registry.keys()) - keys)
        return module

    yield load
    for registry, key in registered:
        registry._plugins.pop(key, None)
    for name in code:
        sys.modules.pop(name.removesuffix(".py"), None)


def test_the_page_has_the_three_examples():
    assert set(examples()) == {"colour_segmenter.py", "folder_dataset.py", "unanimous_vote.py"}
    assert len(examples()["colour_segmenter.py"].splitlines()) <= 45


def test_a_new_segmenter_in_one_file(example, tmp_path, capsys):
    from sagonline.apps.cli import main

    example("colour_segmenter.py")
    folder, _, cams, gt = own_scene(tmp_path / "scene")
    ys, xs = np.nonzero(gt)
    click = f"0:{xs[len(xs) // 2] + 0.5},{ys[len(xs) // 2] + 0.5}"
    out = tmp_path / "out"
    code = main(
        [
            "segment",
            str(folder),
            "--cameras",
            str(folder / "transforms.json"),
            "--segmenter",
            "colour",
            "--click",
            click,
            "--out",
            str(out),
            "--no-record",
            "--segmenter-option",
            "tolerance=30",
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert json.loads((out / "labels.json").read_text())["counts"]["object"] > 0
    cfg = compose_config("eval", "segmenter=colour", "segmenter.tolerance=25")
    assert cfg.segmenter == {"kind": "colour", "name": "colour", "tolerance": 25.0}
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="segmenter.tolerance"):
        compose_config("eval", "segmenter=colour", "segmenter.tolerance=abc")


def test_a_new_dataset_adapter(example, tmp_path):
    from bench.runners.eval import evaluate

    example("folder_dataset.py")
    root = tmp_path / "folder"
    names = [f"v{i}" for i in range(6)]
    cams, scene = llff_scene(root, names, width=48, height=36, with_scene=False)
    for cam, name in zip(cams, names, strict=True):
        write_image(root / "masks" / f"{name}.png", (object_mask(scene, cam) > 0) * 255)
    from sagonline.scene.io import write_ply

    write_ply(root / "point_cloud.ply", scene.gaussians)
    cfg = compose_config(
        "eval",
        "dataset=folder",
        f"dataset.root={root}",
        "segmenter=oracle",
        "progress=false",
        "record=false",
    )
    metrics = evaluate(cfg, tmp_path / "run")
    assert metrics["protocol_id"] == "folder/first-view-clicks3@1"
    assert metrics["miou"] > 0.9 and metrics["scenes"][0]["scene"] == "folder"


def test_a_new_vote_rule_through_both_kernels(example, tiny_task, capsys):
    from sagonline.vote.consensus import VoteConfig, consensus_vote

    example("unanimous_vote.py")
    cfg = VoteConfig(method="unanimous")
    g, cams = tiny_task.gaussians, tiny_task.trajectory
    masks = [m.copy() for m in tiny_task.trajectory_gt]
    masks[1][:, : masks[1].shape[1] // 3] = 0  # disagreement on one side
    ref = consensus_vote(g, cams, masks, 2, cfg, backend="torch")
    fast = consensus_vote(g, cams, masks, 2, cfg, backend="native")
    assert np.array_equal(ref.histogram.numpy(), fast.histogram.numpy())
    assert np.array_equal(ref.labels.numpy(), fast.labels.numpy())
    rgc = consensus_vote(g, cams, masks, 2, VoteConfig(margin=0.0), backend="native")
    # disagreement leaves Gaussians unlabelled (-1)
    assert (ref.labels >= 0).sum() < (rgc.labels >= 0).sum()
    assert compose_config("eval", "consensus=unanimous").consensus.method == "unanimous"
    with pytest.raises(SystemExit):
        compose_config("eval", "consensus=unanimous", "consensus.margin=0.5")
    assert "does not read margin" in capsys.readouterr().err


@pytest.mark.slow
def test_plugins_named_in_the_environment_are_loaded(tmp_path):
    (tmp_path / "colour_segmenter.py").write_text(examples()["colour_segmenter.py"])
    env = {"SAGONLINE_PLUGINS": "colour_segmenter", "PYTHONPATH": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-m", "sagonline", "plugins", "segmenters", "--keys"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**__import__("os").environ, **env},
    )
    assert done.returncode == 0 and "colour" in done.stdout.split(","), done.stderr
    env["SAGONLINE_PLUGINS"] = "no_such_module"
    done = subprocess.run(
        [sys.executable, "-m", "sagonline", "plugins"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**__import__("os").environ, **env},
    )
    assert done.returncode == 2 and "SAGONLINE_PLUGINS names 'no_such_module'" in done.stderr


def test_a_plugin_module_that_registers_nothing_is_refused(tmp_path):
    (tmp_path / "helpers_only.py").write_text("def helper():\n    return 1\n")
    env = {"SAGONLINE_PLUGINS": "helpers_only", "PYTHONPATH": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-m", "sagonline", "plugins"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**__import__("os").environ, **env},
    )
    assert done.returncode == 2 and "registers no plug-in" in done.stderr, done.stderr
