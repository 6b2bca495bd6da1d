"""One typed root config, one default per setting: the dataclasses are Hydra's schemas and the
YAML only selects and overrides, so what a run composes is the dataclass's default unless
something overrides it; a wrong type or an unknown key fails at composition."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from dataclasses import asdict

import pytest
from hydra.errors import ConfigCompositionException

from bench.runners.config import EvalConfig, ScenesConfig
from sagonline.fitting import FitConfig
from sagonline.refine import RefineConfig
from sagonline.vote.consensus import VoteConfig
from sagonline.vote.feedback import FeedbackConfig
from tests.fixtures import compose_config


def test_fit_composes_to_the_dataclass_defaults():
    cfg = compose_config("scenes")
    assert isinstance(cfg, ScenesConfig) and cfg.fit == FitConfig()
    with pytest.raises(ConfigCompositionException):
        compose_config("scenes", "fit.iterations=many")


def test_the_paper_fit_recipe_changes_only_what_it_names():
    paper = compose_config("scenes", "fit=paper").fit
    assert isinstance(paper, FitConfig)
    assert (paper.iterations, paper.densify_until, paper.opacity_reset_every) == (
        30000,
        15000,
        3000,
    )
    changed = {k for k, v in asdict(paper).items() if v != getattr(FitConfig(), k)}
    assert changed == {
        "iterations",
        "max_side",
        "densify_from",
        "densify_until",
        "opacity_reset_every",
        "prune_opacity",
        "max_gaussians",
        "dist_from",
        "normal_from",
        "checkpoint_every",
    }
    assert paper.view_clearance == FitConfig().view_clearance  # our regularisers kept


@pytest.mark.parametrize("method", ["rgc", "flashsplat", "weighted_mean"])
def test_consensus_composes_to_the_dataclass_defaults(method):
    assert compose_config("eval", f"consensus={method}").consensus == VoteConfig(method=method)


def test_refine_composes_to_the_dataclass_defaults():
    refine = compose_config("eval", "refine=student").refine
    assert {k: v for k, v in asdict(refine).items() if k != "enabled"} == asdict(RefineConfig())
    assert refine.enabled and not compose_config("eval").refine.enabled
    with pytest.raises(ConfigCompositionException):
        compose_config("eval", "refine=student", "refine.max_steps=many")


def test_pipeline_settings_defaults_are_the_eval_config_defaults():
    from bench.runners.job import settings_from
    from sagonline.pipeline import PipelineSettings

    composed = asdict(settings_from(compose_config("eval")))
    defaults = asdict(PipelineSettings())
    composed.pop("progress"), defaults.pop("progress")  # CI=true turns progress off
    assert composed == defaults


def test_feedback_composes_to_the_dataclass_defaults():
    assert compose_config("eval", "feedback=on").feedback == FeedbackConfig(enabled=True)
    assert compose_config("eval").feedback == FeedbackConfig()
    with pytest.raises(ConfigCompositionException):
        compose_config("eval", "feedback=on", "feedback.every=often")


@pytest.mark.slow
def test_the_root_config_is_typed_all_the_way_down():
    cfg = compose_config("eval")
    assert isinstance(cfg, EvalConfig)
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        assert type(value).__module__ != "omegaconf.dictconfig", f.name
    assert isinstance(cfg.dataset, dict) and isinstance(cfg.segmenter, dict)  # plug-in nodes
    with pytest.raises(ConfigCompositionException):
        compose_config("eval", "recrod=false")  # an unknown key, named at composition
    with pytest.raises(SystemExit):
        compose_config("eval", "consensus.margin=2")  # out of range: stops before any work


@pytest.mark.parametrize("schema", [EvalConfig, ScenesConfig])
def test_every_root_setting_is_documented_on_its_field(schema):
    """A docstring under each plain field (nested settings dataclasses document their own)."""
    tree = ast.parse(inspect.getsource(schema))
    body = tree.body[0].body
    documented = {
        node.target.id
        for node, nxt in zip(body, body[1:], strict=False)
        if isinstance(node, ast.AnnAssign)
        and isinstance(nxt, ast.Expr)
        and isinstance(nxt.value, ast.Constant)
    }
    nested = {f.name for f in dataclasses.fields(schema) if dataclasses.is_dataclass(f.type)}
    nested |= {
        f.name for f in dataclasses.fields(schema) if f.default_factory is not dataclasses.MISSING
    }
    plain = {f.name for f in dataclasses.fields(schema)} - nested
    assert plain <= documented, sorted(plain - documented)
