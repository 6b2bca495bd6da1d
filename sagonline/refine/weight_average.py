"""The student's weights averaged over its last steps, to answer from (`refine.ema_span`).

Between two points of its training the student's answer can swing by several points of mIoU
(docs/real_captures.md, "Along the training"), and the plateau rule stops it at one such point.
An exponential moving average of the weights over about `span` steps answers like the
neighbourhood of that point. The average is torch's `AveragedModel` over parameters and buffers
(the norm layers' running statistics too), each step weighing 2 / (span + 1) (pandas' `span`),
or 1 / n while that is larger (the plain mean of the first n steps, so the untrained weights
never linger in it).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel


def span_average(span: int):
    """AveragedModel's `multi_avg_fn` for an exponential average over about `span` steps, the
    plain mean while fewer than (span + 1) / 2 steps were averaged."""

    @torch.no_grad()
    def update(averaged: list[torch.Tensor], current: list[torch.Tensor], n_averaged) -> None:
        weight = max(2.0 / (span + 1), 1.0 / (int(n_averaged) + 1))
        if torch.is_floating_point(averaged[0]):
            torch._foreach_lerp_(averaged, current, weight)
        else:  # counters (a norm layer's batches tracked): the current one
            for a, c in zip(averaged, current, strict=True):
                a.copy_(c)

    return update


class WeightAverage:
    """A moving average of a model's weights and buffers over about `span` steps."""

    def __init__(self, model: nn.Module, span: int):
        if span < 1:
            raise ValueError(f"ema_span={span}: must be >= 1 step")
        self.averaged = AveragedModel(model, multi_avg_fn=span_average(span), use_buffers=True)

    @property
    def model(self) -> nn.Module:
        """The averaged copy of the model, to answer with."""
        return self.averaged.module

    @property
    def steps(self) -> int:
        """How many training steps went into the average."""
        return int(self.averaged.n_averaged)

    def update(self, model: nn.Module) -> None:
        """Fold `model`'s weights after one more step into the average."""
        self.averaged.update_parameters(model)

    def state_dict(self) -> dict:
        return self.averaged.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.averaged.load_state_dict(state)
