"""How far two correct float32 evaluations of one view's blend weights may differ, per Gaussian.

A blend vote adds w = alpha_i T_i, T_i = prod_{j<i} (1 - alpha_j), per (pixel, Gaussian) pair.
Two implementations that evaluate the same formulas in float32 in another order (the PyTorch
reference, the Triton kernel on a GPU with fused multiply-adds and an approximate exp) differ
in two ways, bounded here from the reference's own trace:

1. Drift, continuous: alpha carries a relative error of at most r_a = 16u (u = 2^-24: the exp
   approximation's 2 ulp, the power's products and sums in another order) and each factor
   (1 - alpha_j) one of at most 2u + r_a alpha_j / (1 - alpha_j). Over a walk that stops at
   T = eps, sum_j alpha_j / (1 - alpha_j) <= 21.5 ln(1/eps) (alpha <= 0.99 gives alpha / (1 -
   alpha) <= 21.5 (-ln(1 - alpha)), and sum_j -ln(1 - alpha_j) = ln(1/T)), and there are at
   most 1 + 255 ln(1/T) factors of alpha >= 1/255. So one weight's relative error is at most
   rho(T) = r_a (1 + 21.5 ln(1/T)) + 2u (1 + 255 ln(1/T)) + 256u (the kernel sums a tile's
   256 pixels in float32 before its atomic add), and a Gaussian's sum of such weights at most
   the same rho of its smallest T.
2. Flips, discontinuous: a decision that lies within the other evaluation's rounding of its
   threshold can go the other way: the 3-sigma cutoff (power >= -4.5, rho <= 9), alpha >=
   1/255, the walk's stop T > eps. A flipped pair moves its own weight by up to its whole
   alpha T (at the cutoff alpha jumps from opacity * e^-4.5 to 0) and every later weight on
   that pixel by up to that alpha. No relative tolerance bounds this; its size is bounded per
   Gaussian by what lies on the pixels where such a decision is close: the Gaussian's whole
   weight there, plus one jump, plus eps for a walk that may go on past its stop.

`blend_bound` returns, per Gaussian and label, drift + flips; a correct implementation lies
within it, and a wrong one (a factor missing, a pair counted twice, T after instead of before)
does not (tests/render/test_vote_op.py checks both ways).
"""

from __future__ import annotations

import math
import sys

import torch

from sagonline.render.projection import ALPHA_MIN, SIGMA_CUTOFF, SURFEL_FILTER_INV_SQ, project
from sagonline.render.rasterize import TraceChunk, TraceRequest, rasterize
from sagonline.render.rule import VoteRule
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

U = 2.0**-24  # float32 unit roundoff
R_ALPHA = 16 * U


def drift(t: torch.Tensor) -> torch.Tensor:
    """rho(T): the relative error bound of a weight whose transmittance before it is T."""
    log = torch.log(1.0 / t.double().clamp_min(1e-30))
    return R_ALPHA * (1 + 21.5 * log) + 2 * U * (1 + 255 * log) + 256 * U


def _decisions(kind: str, params: torch.Tensor, px: torch.Tensor, py: torch.Tensor):
    """For each candidate (splat, pixel) of `splat_response`'s arguments: the cutoff quantity
    (power for 3DGS, rho for 2DGS) and the unclipped alpha, in float64, and the float32 error
    of that quantity (measured against float64: another float32 order differs by a few such)."""

    def quantities(p, x, y):
        mx, my, opac = (p[..., i : i + 1] for i in range(3))
        dx, dy = x - mx, y - my
        if kind == "3dgs":
            a, b, c = (p[..., 4 + i : 5 + i] for i in range(3))
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            scale = 0.5 * (a.abs() * dx * dx + c.abs() * dy * dy) + (b * dx * dy).abs()
            return power, scale, opac * torch.exp(power)
        m = [p[..., 4 + i : 5 + i] for i in range(9)]
        k0, k1, k2 = x * m[6] - m[0], x * m[7] - m[1], x * m[8] - m[2]
        l0, l1, l2 = y * m[6] - m[3], y * m[7] - m[4], y * m[8] - m[5]
        pz = k0 * l1 - k1 * l0
        pz = torch.where(pz.abs() < 1e-12, torch.full_like(pz, 1e-12), pz)
        u = (k1 * l2 - k2 * l1) / pz
        v = (k2 * l0 - k0 * l2) / pz
        rho = torch.minimum(u * u + v * v, SURFEL_FILTER_INV_SQ * (dx * dx + dy * dy))
        return rho, rho.abs(), opac * torch.exp(-0.5 * rho)

    q64, scale, alpha64 = quantities(params.double(), px.double(), py.double())
    q32, _, _ = quantities(params.float(), px.float(), py.float())
    error = 4 * (q32.double() - q64).abs() + 8 * U * scale + 1e-12
    return q64, error, alpha64


def blend_bound(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [H, W] long
    num_labels: int,
    rule: VoteRule,
) -> tuple[torch.Tensor, torch.Tensor]:  # [N, K] reference (float64), [N, K] bound
    """The reference histogram of one view's blend votes and, per entry, how far another
    correct float32 evaluation may lie from it (see the module docstring)."""
    if rule.weighting != "blend" or rule.delta is not None:
        raise ValueError("blend_bound covers the blend rule without a distance rule")
    n, k, width = len(gaussians), num_labels, camera.width
    flat = labels.flatten().to(gaussians.device)
    ref = torch.zeros(n, k, dtype=torch.float64, device=gaussians.device)
    pairs: list[TraceChunk] = []
    near_pixels: list[torch.Tensor] = []
    cutoff = -0.5 * SIGMA_CUTOFF**2

    module = sys.modules["sagonline.render.rasterize"]
    response = module.splat_response

    def watched(kind, params, px, py):  # the reference's own candidates, decisions measured
        q, err, alpha = _decisions(kind, params, px, py)
        limit = cutoff if kind == "3dgs" else SIGMA_CUTOFF**2
        near_cut = (q - limit).abs() <= err
        alpha_err = alpha * (err + R_ALPHA)
        near_min = (alpha - ALPHA_MIN).abs() <= alpha_err
        near = (near_cut | near_min) & (alpha >= ALPHA_MIN * 0.5)
        if near.any():
            pix = (py.floor().long() * width + px.floor().long()).expand_as(near)
            near_pixels.append(pix[near])
        return response(kind, params, px, py)

    def keep(chunk: TraceChunk) -> None:
        pairs.append(chunk)

    module.splat_response = watched
    try:
        rasterize(gaussians, camera, trace=TraceRequest(keep, eps=rule.eps, delta=None))
    finally:
        module.splat_response = response
    pixel = torch.cat([c.pixel for c in pairs])
    splat = torch.cat([c.gaussian for c in pairs])
    t_before = torch.cat([c.transmittance for c in pairs]).double()
    alpha = torch.cat([c.alpha for c in pairs]).double()
    weight = alpha * t_before
    index = splat * k + flat[pixel]
    ref.view(-1).index_add_(0, index, weight)

    # 1. drift: each weight by rho of its own T
    bound = torch.zeros_like(ref)
    bound.view(-1).index_add_(0, index, weight * drift(t_before))

    # 2. flips. Decision pixels: a candidate's cutoff or alpha >= 1/255 lies within rounding
    # of its threshold: every weight there may change, and a pair may appear (one jump).
    hw = camera.height * width
    decision = torch.zeros(hw, dtype=torch.bool, device=ref.device)
    if near_pixels:
        found = torch.cat(near_pixels)
        decision[found[(found >= 0) & (found < hw)]] = True
    # Stop pixels: the walk's last T, or a pair's T before it, lies within rounding of eps (two
    # opaque splats, alpha clipped to 0.99, leave T = 0.01^2 = 1e-4: the blend rule's own eps).
    # A pair that close may vanish, and the walk may go on past its stop by at most eps.
    t_after = t_before * (1 - alpha)
    last = torch.full((hw,), 1.0, dtype=torch.float64, device=ref.device)
    last.scatter_reduce_(0, pixel, t_after, "amin")
    margin = 4 * drift(torch.tensor(rule.eps)).item() * rule.eps
    close = (t_before - rule.eps).abs() <= margin
    stop = (last - rule.eps).abs() <= margin
    stop[pixel[close]] = True
    vanish = decision[pixel] | close
    bound.view(-1).index_add_(0, index[vanish], weight[vanish])

    # one jump (decision pixels) and eps past a stop, to the pixel's label, for each Gaussian
    # whose 3-sigma box holds the pixel and (stop pixels) lies behind the walk's last pair
    proj = project(gaussians, camera, with_colors=False)
    depth = torch.full((n,), float("inf"), dtype=torch.float64, device=ref.device)
    depth[proj.ids] = proj.depths.double()
    is_last = t_after == last[pixel]
    last_depth = torch.full((hw,), float("inf"), dtype=torch.float64, device=ref.device)
    last_depth.scatter_reduce_(0, pixel[is_last], depth[splat[is_last]], "amin")
    jump = (proj.opacities.double() * math.exp(cutoff)).clamp_min(ALPHA_MIN) * (1 + 1e-3)
    for pixels, per_splat, behind_only in (
        (decision, jump + rule.eps * (1 + 1e-3), False),
        (stop & ~decision, torch.full_like(jump, rule.eps * (1 + 1e-3)), True),
    ):
        ys, xs = torch.nonzero(pixels.view(camera.height, width), as_tuple=True)
        if not len(xs):
            continue
        cx, cy, box = xs.double() + 0.5, ys.double() + 0.5, proj.bbox.double()
        inside = (
            (cx[None] >= box[:, :1])
            & (cx[None] <= box[:, 1:2])
            & (cy[None] >= box[:, 2:3])
            & (cy[None] <= box[:, 3:4])
        )
        lin = ys * width + xs
        if behind_only:
            inside &= proj.depths.double()[:, None] >= last_depth[lin][None]
        m_idx, p_idx = torch.nonzero(inside, as_tuple=True)
        bound.view(-1).index_add_(0, proj.ids[m_idx] * k + flat[lin[p_idx]], per_splat[m_idx])
    return ref, bound
