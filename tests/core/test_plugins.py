"""Plug-ins: one that raises at import or takes a registered name is named with its module; a
config outside its package is refused; export builds plug-ins only from the registry; the
built-ins' declared keys and vote settings are what their modules register."""

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


def test_each_built_in_module_registers_the_keys_declared_for_it():
    """The command line's choices come from the declarations (`Registry.names`, no import):
    they are the keys the built-in modules register, module by module."""
    from sagonline.core.plugins import DATASETS, SEGMENTERS, VOTE_RULES

    for registry in (SEGMENTERS, DATASETS, VOTE_RULES):
        registered: dict[str, list[str]] = {}
        for plugin in registry:
            registered.setdefault(plugin.module, []).append(plugin.key)
        for module, keys in registry.builtins.items():
            assert sorted(registered.get(module, [])) == sorted(keys), (registry.what, module)
        assert registry.names() == registry.keys()


def test_names_are_read_without_import_and_a_wrong_declaration_is_refused(tmp_path, monkeypatch):
    """`names` reads the declarations and imports nothing; loading checks them against what the
    module registers, and a disagreement names the module and both lists."""
    import sys
    import types

    from sagonline.core.plugins import PluginError, Registry

    holder = types.ModuleType("declared_holder")
    monkeypatch.setitem(sys.modules, "declared_holder", holder)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("SAGONLINE_PLUGINS", raising=False)
    (tmp_path / "declared_plugins.py").write_text(
        "from dataclasses import dataclass\nimport declared_holder\n"
        "@dataclass\nclass C:\n    pass\n"
        "declared_holder.REGISTRY.register('a', C, lambda c: c)\n"
    )
    holder.REGISTRY = Registry("thing", "sagonline.no_such_group", {"declared_plugins": ("a",)})
    assert holder.REGISTRY.names() == ["a"] and "declared_plugins" not in sys.modules
    assert holder.REGISTRY.keys() == ["a"] and "declared_plugins" in sys.modules
    monkeypatch.delitem(sys.modules, "declared_plugins")
    holder.REGISTRY = Registry("thing", "sagonline.no_such_group", {"declared_plugins": ("a", "b")})
    with pytest.raises(PluginError, match=r"declared_plugins registers \['a'\].*\['a', 'b'\]"):
        holder.REGISTRY.keys()


def test_the_vote_controls_from_the_declarations_are_the_registry_s(monkeypatch):
    """`segment`'s vote flags and the viewer's panel read each method's settings from
    `vote.settings` without importing the vote: the same controls the registry gives."""
    from sagonline.core.plugins import VOTE_RULES
    from sagonline.vote import settings

    monkeypatch.setattr(VOTE_RULES, "declared_only", lambda: True)
    declared = settings.vote_setting_specs()
    monkeypatch.setattr(VOTE_RULES, "declared_only", lambda: False)
    VOTE_RULES.keys()
    builtin = {k: p for k, p in VOTE_RULES._plugins.items() if k in settings.BUILTIN_METHODS}
    monkeypatch.setattr(VOTE_RULES, "_plugins", builtin)  # without another test's plug-ins
    assert settings.vote_setting_specs() == declared
    assert {p.key: p.config for p in VOTE_RULES} == settings.BUILTIN_METHODS


def test_an_installed_package_s_entry_point_is_loaded_under_the_documented_group(tmp_path):
    """A package that declares a segmenter as docs/extending.md says (an entry point in the
    group it names) is listed by `sagonline plugins` and offered by `segment --help`; the page
    names each registry's group."""
    import re
    import subprocess
    import sys

    from sagonline.core.plugins import DATASETS, SEGMENTERS, VOTE_RULES
    from tests.fixtures import ROOT

    page = (ROOT / "docs" / "extending.md").read_text()
    bullet = page[page.index("installed package's entry point") :].split("\n- ")[0]
    documented = re.findall(r'"(sagonline\.\w+)"', bullet)
    assert sorted(documented) == sorted(r.group for r in (SEGMENTERS, DATASETS, VOTE_RULES))
    dist = tmp_path / "my_segmenter-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-segmenter\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{SEGMENTERS.group}]\nmine = my_segmenter\n")
    (tmp_path / "my_segmenter.py").write_text(
        "from dataclasses import dataclass\nfrom sagonline.core.plugins import SEGMENTERS\n"
        "@dataclass\nclass MineConfig:\n    pass\n"
        "@SEGMENTERS.register('mine', MineConfig)\nclass Mine:\n"
        "    '''Mine: a segmenter an installed package declares.'''\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    env.pop("SAGONLINE_PLUGINS", None)
    for command in (["plugins", "segmenters"], ["segment", "--help"]):
        run = subprocess.run(
            [sys.executable, "-m", "sagonline", *command],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
        )
        assert run.returncode == 0 and "mine" in run.stdout, (command, run.stderr)
