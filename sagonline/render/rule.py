"""The vote's rule: which (pixel, Gaussian) pairs of one view vote, and for how much; and the
label render's: how much of a pixel its labelled Gaussians must make up (`LABEL_MIN_WEIGHT`).

One frozen `VoteRule` travels unchanged from the vote's settings (`consensus.eps`, `consensus.delta`
on the command line; `vote.consensus.VoteConfig.rule`) through the op (`render.vote.vote_into`)
into every implementation (the PyTorch reference, the C++ kernel, the Triton kernel), under the
same names everywhere: `eps` and `delta`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

WEIGHTINGS = ("count", "blend")


@dataclass(frozen=True)
class VoteRule:
    """eps: a Gaussian votes only while the transmittance before it is T_i > eps, and a pixel's
    walk stops once T <= eps; delta: ... and only if its projected centre lies within delta px
    of the pixel centre (None: no distance rule, the one way to say so); weighting: count (+1
    per pair, the paper's RGC) or blend (alpha_i T_i, FlashSplat and the weighted mean).

    The paper's eps and delta are defined here and nowhere else: rgc's settings
    (`vote.settings.RgcSettings`, and through them the `consensus.*` settings) take their
    defaults from these. How a histogram becomes labels (min_votes, margin) is the vote
    method's business, not the kernels'."""

    eps: float = 0.01
    delta: float | None = 2.0
    weighting: str = "count"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.eps) and 0 <= self.eps < 1):
            raise ValueError(f"vote rule eps={self.eps!r}: must be a transmittance in [0, 1)")
        if self.delta is not None and not (math.isfinite(self.delta) and self.delta > 0):
            raise ValueError(f"vote rule delta={self.delta!r}: must be > 0 px, or None (off)")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"vote rule weighting={self.weighting!r}: one of {WEIGHTINGS}")


LABEL_MIN_WEIGHT = 0.2
"""The label render's default: a pixel takes a label where labelled Gaussians make up this much
of it (the project's choice; the real captures' chosen setting is 0.5, docs/real_captures.md)."""

__all__ = ["LABEL_MIN_WEIGHT", "WEIGHTINGS", "VoteRule"]
