"""The plateau rule that stops the student's training: its smoothed loss stopped improving."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Plateau:
    """When the smoothed loss stops improving. The loss is smoothed by an exponential moving
    average (0.9); its best value counts only after `warmup` steps, so one lucky first batch
    cannot set a best that the noisy steps after it never beat (which made "converged" mean
    "the first `patience` steps ended"); then `patience` steps without a gain of `min_delta`
    over the best mean converged. `best_step` is the step of the best smoothed loss."""

    patience: int
    min_delta: float
    warmup: int
    ema: float | None = None
    best: float = float("inf")
    best_step: int = -1
    since_best: int = 0
    steps: int = 0

    def add(self, loss: float) -> None:
        self.ema = loss if self.ema is None else 0.9 * self.ema + 0.1 * loss
        self.steps += 1
        if self.steps < self.warmup:
            return
        if self.ema < self.best - self.min_delta:
            self.best, self.best_step, self.since_best = self.ema, self.steps - 1, 0
        else:
            self.since_best += 1

    @property
    def converged(self) -> bool:
        return self.steps >= self.warmup and self.since_best >= self.patience
