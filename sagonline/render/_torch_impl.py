"""The vote's readable reference, twin of the compiled kernels (`native.vote_into`,
`triton_vote.vote_into`): the same op, `vote_into(gaussians, camera, labels, hist, rule)`,
written with PyTorch ops on `rasterize`'s streamed trace, on the CPU or CUDA. The tests check
every fast implementation against it, pair for pair."""

from __future__ import annotations

import torch

from sagonline.render.rasterize import TraceChunk, TraceRequest, rasterize
from sagonline.render.rule import VoteRule
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians


def vote_into(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [H, W] long, the view's mask
    hist: torch.Tensor,  # [N, K] float64, added into
    rule: VoteRule,
    *,
    via: str = "torch",
) -> int:
    """One view's votes under `rule`, added into hist: the (pixel, Gaussian) pairs the rule
    keeps, streamed from a render's trace (`rasterize`, or gsplat's ids with via="gsplat") and
    reduced by `add_pairs`; returns how many pairs voted."""
    flat = labels.flatten()
    cast = [0]

    def add(chunk: TraceChunk) -> None:
        cast[0] += add_pairs(hist, flat, chunk, rule.weighting)

    request = TraceRequest(add, eps=rule.eps, delta=rule.delta)
    if via == "gsplat":
        from sagonline.render.gsplat_backend import rasterize_gsplat

        rasterize_gsplat(gaussians, camera, trace=request)
    else:
        rasterize(gaussians, camera, trace=request)
    return cast[0]


def add_pairs(
    hist: torch.Tensor,  # [N, K] float64
    labels: torch.Tensor,  # [H * W] long, the view's mask
    chunk: TraceChunk,
    weighting: str,
) -> int:
    """Add the votes of traced (pixel, Gaussian) pairs, already filtered by the rule
    (`TraceRequest.keeps`), to hist; returns the votes cast."""
    k = hist.shape[1]
    index = chunk.gaussian * k + labels[chunk.pixel]
    if weighting == "count":
        weight = torch.ones_like(index, dtype=hist.dtype)
    else:
        weight = (chunk.alpha * chunk.transmittance).to(hist.dtype)
    hist.view(-1).scatter_add_(0, index, weight)
    return int(index.numel())


__all__ = ["add_pairs", "vote_into"]
