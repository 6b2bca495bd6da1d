"""Plug-ins: one that raises at import or takes a registered name is named with its module; a
config outside its package is refused; export builds plug-ins only from the registry."""

from __future__ import annotations

import json
import os

import pytest

from sagonline.apps.cli import main
from tests.refusals import error_line, one_error_line, run_python


def test_a_plugin_that_raises_at_import_is_named(tmp_path):
    (tmp_path / "broken_plugin.py").write_text("raise RuntimeError('the plug-in is broken')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "SAGONLINE_PLUGINS": "broken_plugin"}
    for command in (["sagonline", "plugins"], ["bench.runners.eval", "record=false"]):
        code, err, _ = run_python(*command, env=env)
        assert code == 2, (command, err)
        one_error_line(err, "'broken_plugin'", "RuntimeError: the plug-in is broken")
    env["SAGONLINE_PLUGINS"] = "../x"
    code, err, _ = run_python("sagonline", "plugins", env=env)
    assert code == 2
    one_error_line(err, "'../x': not a module name")


def test_a_plugin_taking_a_registered_name_is_named_with_its_module(tmp_path):
    (tmp_path / "thief.py").write_text(
        "from dataclasses import dataclass\n"
        "from sagonline.core.plugins import SEGMENTERS\n"
        "@dataclass\nclass C:\n    pass\n"
        "@SEGMENTERS.register('classical', C)\nclass Mine:\n    pass\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "SAGONLINE_PLUGINS": "thief"}
    code, err, _ = run_python("sagonline", "plugins", env=env)
    assert code == 2
    one_error_line(err, "'classical' is registered twice", "sagonline.segment.classical", "thief")


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
        error_line(capsys)
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
