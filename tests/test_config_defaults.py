"""One default per setting: the YAML in conf/ and the dataclasses must not drift apart.

Until the dataclasses are Hydra's schema (the YAML then only selects and overrides), this test
is what keeps the two copies equal: a default changed on one side fails here, naming the key.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from sagonline.consensus import VoteConfig
from sagonline.fit import FitConfig

CONF = Path(__file__).resolve().parents[1] / "conf"
INTERPOLATED = ("seed", "device")  # set from the top-level config


def _drift(defaults: dict, yaml: dict, skip=()) -> list[str]:
    out = []
    for key, value in yaml.items():
        if key in skip or key in INTERPOLATED or key == "defaults":
            continue
        if key not in defaults:
            out.append(f"{key}: in the YAML only")
            continue
        mine = list(defaults[key]) if isinstance(defaults[key], tuple) else defaults[key]
        if mine != value:
            out.append(f"{key}: dataclass {defaults[key]!r}, YAML {value!r}")
    return out


def test_fit_defaults_equal_the_scenes_yaml():
    yaml = OmegaConf.to_container(OmegaConf.load(CONF / "scenes.yaml").fit)
    assert _drift(asdict(FitConfig()), yaml, skip=("max_side",)) == []
    assert set(asdict(FitConfig())) <= set(yaml)  # every setting can be set from the YAML


@pytest.mark.parametrize("method", ["rgc", "flashsplat", "weighted_mean"])
def test_vote_defaults_equal_the_consensus_yaml(method):
    yaml = OmegaConf.to_container(OmegaConf.load(CONF / "consensus" / f"{method}.yaml"))
    assert _drift(asdict(VoteConfig()), yaml, skip=("method",)) == []
