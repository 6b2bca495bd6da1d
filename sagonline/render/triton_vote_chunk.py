"""The chunked vote in Triton: `triton_vote`'s vote, CHUNK splats of a tile's list at a time.

`_vote_chunk_kernel` takes the tile lists of `triton_vote.tile_view` and gives what the splat
walk's vote gives (the (N, K) histogram and the pairs that voted per tile), by the same rule:
a chunk's parameters are loaded together, alpha is a (256 pixels, CHUNK) block, the
transmittance before each splat a running product along the chunk (tl.cumprod), and the
chunk's votes per label one (CHUNK, 256) x (256, KP) product (tl.dot). `triton_vote.vote_into`
launches it when SAGONLINE_TRITON_VOTE is chunk16, chunk32 or chunk16w16 (16 warps a tile),
and, with it unset, chunk16 for a counting rule on CUDA: faster than the walk there on both
bench scenes in two GPU runs (`backends.DEFAULT_TRITON_VOTE`; docs/performance.md, "The chunked
vote").
"""

from __future__ import annotations

import torch

# triton_vote first: without CUDA it chooses Triton's interpreter before triton is imported
from sagonline.render.triton_vote import TILE, TiledView, _kernel

# isort: split
import triton
import triton.language as tl

from sagonline.render.rule import VoteRule

# Warps per tile program by default: on 8 warps (256 threads) a (256, CHUNK) float32 block is
# CHUNK values a thread (`backends.TRITON_VOTE_KERNELS` names the variants).
CHUNK_WARPS = 8


@_kernel
def _vote_chunk_kernel(
    params_ptr,
    order_ptr,
    offsets_ptr,
    counts_ptr,
    ids_ptr,
    pixel_labels_ptr,
    out_ptr,
    cast_ptr,
    width,
    height,
    tiles_x,
    num_labels,
    eps,
    delta,
    SURFEL: tl.constexpr,
    WEIGHTED: tl.constexpr,
    USE_DISTANCE: tl.constexpr,
    TILE: tl.constexpr,
    KP: tl.constexpr,
    NP: tl.constexpr,
    CHUNK: tl.constexpr,
):
    """The vote of `_walk_kernel` (same inputs and outputs, same rule) taken CHUNK splats at a
    time: a chunk's parameters are loaded together, alpha is a (pixels, CHUNK) block, the
    transmittance before each splat a running product along the chunk (tl.cumprod), and the
    chunk's votes per label one (CHUNK, pixels) x (pixels, KP) product (tl.dot; exact for counts
    in fp16, blend weights in fp32 "ieee"). The splat walk's loop carries one splat's loads and
    a block reduction per step; this one a chunk's. KP >= 16 (tl.dot's smallest side).

    Why one function: as `_walk_kernel`'s (its splat response repeats the walk's, which says
    why that is not a shared helper)."""
    tile = tl.program_id(0)
    q = tl.arange(0, TILE * TILE)
    x0 = (tile % tiles_x) * TILE
    y0 = (tile // tiles_x) * TILE
    x = x0 + q % TILE
    y = y0 + q // TILE
    inside = (x < width) & (y < height)
    px = (x.to(tl.float32) + 0.5)[:, None]
    py = (y.to(tl.float32) + 0.5)[:, None]
    kk = tl.arange(0, KP)
    lab = tl.load(pixel_labels_ptr + y * width + x, mask=inside, other=0)
    onehot = (lab[:, None] == kk[None, :]).to(tl.float32)
    # a pixel outside the view, or every pixel when eps >= 1, never votes: T = 0 <= eps
    T = tl.where(inside & (eps < 1.0), 1.0, 0.0)
    cast = tl.zeros((TILE * TILE,), tl.int32)
    start = tl.load(offsets_ptr + tile)
    n = tl.load(counts_ptr + tile)
    b = tl.arange(0, CHUNK)
    j = 0
    alive = tl.reduce((eps < T).to(tl.int32), 0, tl.standard._elementwise_max) > 0
    while (j < n) & alive:
        valid = j + b < n
        s = tl.load(order_ptr + start + j + b, mask=valid, other=0)
        base = params_ptr + s * NP
        mx = tl.load(base, mask=valid, other=0.0)[None, :]
        my = tl.load(base + 1, mask=valid, other=0.0)[None, :]
        opac = tl.load(base + 2, mask=valid, other=0.0)[None, :]
        dx = px - mx
        dy = py - my
        if SURFEL:  # projection.splat_response, 2DGS: ray-splat intersection
            m0 = tl.load(base + 4, mask=valid, other=0.0)[None, :]
            m1 = tl.load(base + 5, mask=valid, other=0.0)[None, :]
            m2 = tl.load(base + 6, mask=valid, other=0.0)[None, :]
            m3 = tl.load(base + 7, mask=valid, other=0.0)[None, :]
            m4 = tl.load(base + 8, mask=valid, other=0.0)[None, :]
            m5 = tl.load(base + 9, mask=valid, other=0.0)[None, :]
            m6 = tl.load(base + 10, mask=valid, other=0.0)[None, :]
            m7 = tl.load(base + 11, mask=valid, other=0.0)[None, :]
            m8 = tl.load(base + 12, mask=valid, other=1.0)[None, :]
            k0 = px * m6 - m0
            k1 = px * m7 - m1
            k2 = px * m8 - m2
            l0 = py * m6 - m3
            l1 = py * m7 - m4
            l2 = py * m8 - m5
            pz = k0 * l1 - k1 * l0
            pz = tl.where(tl.abs(pz) < 1e-12, 1e-12, pz)
            u = (k1 * l2 - k2 * l1) / pz
            v = (k2 * l0 - k0 * l2) / pz
            rho3d = u * u + v * v
            rho2d = 2.0 * (dx * dx + dy * dy)
            use3d = rho3d <= rho2d
            rho = tl.where(use3d, rho3d, rho2d)
            depth = tl.where(use3d, u * m6 + v * m7 + m8, tl.load(base + 3, mask=valid)[None, :])
            power = -0.5 * rho
            reach = (rho <= 9.0) & (depth > 1e-2)
        else:  # 3DGS: EWA conic
            a = tl.load(base + 4, mask=valid, other=0.0)[None, :]
            bb = tl.load(base + 5, mask=valid, other=0.0)[None, :]
            c = tl.load(base + 6, mask=valid, other=0.0)[None, :]
            power = -0.5 * (a * dx * dx + c * dy * dy) - bb * dx * dy
            reach = power >= -4.5
        alpha = tl.minimum(opac * tl.exp(power), 0.99)  # projection.ALPHA_MAX
        alpha = tl.where(reach & (alpha >= 0.00392156862745098), alpha, 0.0)  # ALPHA_MIN, 1/255
        alpha = tl.where(valid[None, :], alpha, 0.0)
        keep = 1.0 - alpha
        through = T[:, None] * tl.cumprod(keep, 1)  # T after each splat of the chunk
        before = through / keep  # T_i, before it (keep >= 0.01)
        vote = (eps < before) & (alpha > 0)
        if USE_DISTANCE:
            vote = vote & (dx * dx + dy * dy < delta * delta)
        cast += tl.reduce(vote.to(tl.int32), 1, tl.standard._sum_combine)
        if WEIGHTED:
            w = tl.where(vote, alpha * before, 0.0)
            per_label = tl.dot(tl.trans(w), onehot, input_precision="ieee")
        else:  # 0/1 in fp16, summed in fp32: exact
            per_label = tl.dot(tl.trans(vote.to(tl.float16)), onehot.to(tl.float16))
        gid = tl.load(ids_ptr + s, mask=valid, other=0)
        tl.atomic_add(
            out_ptr + gid[:, None] * num_labels + kk[None, :],
            per_label.to(tl.float64),
            mask=valid[:, None] & (kk[None, :] < num_labels) & (per_label > 0),
        )
        T = tl.reduce(through, 1, tl.standard._elementwise_min)  # the chunk's last: T after it
        j += CHUNK
        alive = tl.reduce((eps < T).to(tl.int32), 0, tl.standard._elementwise_max) > 0
    tl.store(cast_ptr + tile, tl.reduce(cast.to(tl.int64), 0, tl.standard._sum_combine))


def vote_chunks(
    view: TiledView,
    hist: torch.Tensor,  # [N, K] float64, added into
    pixel_labels: torch.Tensor,  # [H, W] int32
    cast: torch.Tensor,  # [tiles] int64, pairs that voted per tile
    rule: VoteRule,
    chunk: int,
    warps: int = CHUNK_WARPS,
) -> None:
    """One launch of `_vote_chunk_kernel` over the view's tiles, `chunk` splats a step on
    `warps` warps: the `launch` of `triton_vote.vote_into` that SAGONLINE_TRITON_VOTE picks
    (chunk16, chunk32, chunk16w16)."""
    num_labels = hist.shape[1]
    _vote_chunk_kernel[(view.tiles_x * view.tiles_y,)](
        view.params,
        view.order,
        view.offsets,
        view.counts,
        view.proj.ids,
        pixel_labels,
        hist,
        cast,
        view.width,
        view.height,
        view.tiles_x,
        num_labels,
        float(rule.eps),
        float(rule.delta) if rule.delta is not None else 0.0,
        SURFEL=view.proj.kind == "2dgs",
        WEIGHTED=rule.weighting == "blend",
        USE_DISTANCE=rule.delta is not None,
        TILE=TILE,
        KP=max(16, triton.next_power_of_2(num_labels)),
        NP=view.params.shape[1],
        CHUNK=chunk,
        num_warps=warps,
    )
