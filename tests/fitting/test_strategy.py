"""The densification strategy's opacity rules, on a parameter set of its own."""

from __future__ import annotations

import math

import pytest
import torch

from sagonline.fitting import FitConfig
from sagonline.fitting.strategy import DensifyStrategy


def opacities(alpha: list[float]) -> dict[str, torch.Tensor]:
    a = torch.tensor(alpha)
    return {"opacity_logit": torch.logit(a)}


def strategy(**kw) -> DensifyStrategy:
    cfg = FitConfig(densify_from=10_000, opacity_reset_every=0, densify_until=50, **kw)
    return DensifyStrategy(cfg, torch.zeros(1, 3), extent=1.0)


def test_opacity_decay_scales_every_opacity_only_while_densifying():
    params = opacities([0.8, 0.5, 0.01])
    decaying = strategy(opacity_decay=0.5)
    assert decaying.after_step(params, 10) is None  # no parameter set of its own
    assert torch.allclose(torch.sigmoid(params["opacity_logit"]), torch.tensor([0.4, 0.25, 0.005]))
    decaying.after_step(params, 51)  # after densify_until: left alone
    assert torch.allclose(torch.sigmoid(params["opacity_logit"]), torch.tensor([0.4, 0.25, 0.005]))
    untouched = opacities([0.8, 0.5, 0.01])
    strategy().after_step(untouched, 10)  # 1: off
    assert torch.allclose(untouched["opacity_logit"], opacities([0.8, 0.5, 0.01])["opacity_logit"])
    assert math.isclose(FitConfig().opacity_decay, 1.0)


@pytest.mark.parametrize("decay", [0.0, -0.1, 1.5])
def test_an_opacity_decay_outside_0_1_is_refused(decay):
    with pytest.raises(ValueError, match="opacity_decay"):
        FitConfig(opacity_decay=decay)
