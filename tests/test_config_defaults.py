"""One default per setting: the dataclasses are Hydra's schemas and the YAML only selects and
overrides, so what a run composes is the dataclass's default unless something overrides it."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

import bench.common  # noqa: F401 (registers the schemas)
from sagonline.consensus import VoteConfig
from sagonline.fitting import FitConfig

CONF = str(Path(__file__).resolve().parents[1] / "conf")


def _compose(name: str, *overrides: str):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(name, overrides=list(overrides))


def test_fit_composes_to_the_dataclass_defaults():
    fit = OmegaConf.to_container(_compose("scenes").fit, resolve=True)
    assert fit == {**asdict(FitConfig()), "seed": 0, "device": "cpu"} | {
        "background": list(FitConfig().background)
    }
    with pytest.raises(ConfigCompositionException):
        _compose("scenes", "fit.iterations=many")


@pytest.mark.parametrize("method", ["rgc", "flashsplat", "weighted_mean"])
def test_consensus_composes_to_the_dataclass_defaults(method):
    vote = OmegaConf.to_container(_compose("eval", f"consensus={method}").consensus, resolve=True)
    assert vote == asdict(VoteConfig(method=method))


def test_refine_composes_to_the_dataclass_defaults():
    from sagonline.refine import RefineConfig

    refine = OmegaConf.to_container(_compose("eval", "refine=student").refine, resolve=True)
    assert refine == {**asdict(RefineConfig()), "enabled": True}
    assert _compose("eval").refine == {"enabled": False}
    with pytest.raises(ConfigCompositionException):
        _compose("eval", "refine=student", "refine.max_steps=many")


def test_pipeline_settings_defaults_are_the_eval_config_defaults():
    from bench.common import settings_from
    from sagonline.pipeline import PipelineSettings

    composed = asdict(settings_from(_compose("eval")))
    defaults = asdict(PipelineSettings())
    composed.pop("progress"), defaults.pop("progress")  # CI=true turns progress off
    assert composed == defaults


def test_feedback_composes_to_the_dataclass_defaults():
    from sagonline.feedback import FeedbackConfig

    on = OmegaConf.to_container(_compose("eval", "feedback=on").feedback, resolve=True)
    assert on == asdict(FeedbackConfig(enabled=True))
    off = OmegaConf.to_container(_compose("eval").feedback, resolve=True)
    assert off == asdict(FeedbackConfig())
    with pytest.raises(ConfigCompositionException):
        _compose("eval", "feedback=on", "feedback.every=often")
