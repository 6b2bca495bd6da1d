"""The fused GPU walk in Triton: trace-and-vote, and the label renders, one launch per view.

One kernel, `_walk_kernel`: a program per 16x16 tile walks the tile's depth-sorted splats once
(the tile lists of `rasterize.bin_tiles`, over the boxes where alpha can reach 1/255:
`projection.reach_boxes`), keeping T for its 256 pixels, and does one of:
- the vote: a splat votes at the pixels where T_i > eps, alpha_i > 0 and (with a distance
  rule) its projected centre lies within delta px; the tile's votes are summed per label
  first, so a splat costs one masked atomic add of K values per tile, not one atomic per pixel,
  and none at all when its centre is farther than delta from every pixel of the tile. The walk
  ends once every pixel's T <= eps.
- the composite: per-splat feature rows (one-hot labels, or colours) composited by the rules of
  `rasterize` (a pixel ends at the splat that would take T under t_stop), the most visible
  Gaussian per pixel and, for images, the depth and the final T: the label renders and the
  image renderer of a CUDA machine without gsplat (`triton_composite.py`; no gradients).

A second vote kernel, `triton_vote_chunk._vote_chunk_kernel`, takes the same tile lists CHUNK
splats at a time; which one the vote op launches is `backends.triton_vote_kernel(weighting)`
(SAGONLINE_TRITON_VOTE: walk, chunk16, chunk32 or chunk16w16; unset, chunk16 for counts and the
walk for blends on CUDA, the walk on the CPU; docs/performance.md, "The chunked vote").

Alpha is `projection.splat_response`'s (3DGS conics, 2DGS ray-splat intersection). The kernel
is compiled by `triton.jit` for CUDA tensors at run time (no CUDA toolkit needed) or, in a
process without CUDA, run by Triton's interpreter on CPU tensors, which is how CI tests it.
Counts are exact; blend weights are summed per tile in float32 and added to the float64
histogram by atomics, whose order on a GPU is not fixed (a weight's last bits may vary).
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, replace

import torch

# Without CUDA the kernel can only run in Triton's interpreter, and Triton reads that choice when
# it is first imported (its own library functions are built for one mode): set it before then.
if not torch.cuda.is_available() and "triton" not in sys.modules:
    os.environ.setdefault("TRITON_INTERPRET", "1")

import triton  # noqa: E402
import triton.language as tl  # noqa: E402

from sagonline.render.projection import ProjectedSplats, project, reach_boxes  # noqa: E402
from sagonline.render.rasterize import bin_tiles  # noqa: E402
from sagonline.render.rule import VoteRule  # noqa: E402
from sagonline.scene.cameras import Camera  # noqa: E402
from sagonline.scene.gaussians import Gaussians  # noqa: E402

TILE = 16
# Compiled for CUDA, or interpreted on the CPU (no CUDA, or TRITON_INTERPRET=1): one mode per
# process, as Triton's own decorator decides.
INTERPRET = bool(triton.knobs.runtime.interpret)


def _kernel(fn):
    if INTERPRET:
        from triton.runtime.interpreter import InterpretedFunction

        return InterpretedFunction(fn)
    return triton.jit(fn)


@_kernel
def _walk_kernel(
    params_ptr,
    order_ptr,
    offsets_ptr,
    counts_ptr,
    ids_ptr,
    pixel_labels_ptr,
    rows_ptr,
    out_ptr,
    best_ptr,
    depth_ptr,
    trans_ptr,
    cast_ptr,
    width,
    height,
    tiles_x,
    num_labels,
    eps,
    delta,
    t_stop,
    COMPOSITE: tl.constexpr,
    IMAGE: tl.constexpr,
    SURFEL: tl.constexpr,
    WEIGHTED: tl.constexpr,
    USE_DISTANCE: tl.constexpr,
    TILE: tl.constexpr,
    KP: tl.constexpr,
    NP: tl.constexpr,
    CHECK_EVERY: tl.constexpr,
):
    """One tile's walk. COMPOSITE=False, the vote: pixel_labels (H*W,) -> out (N, K) float64
    histogram, and the tile's count of pairs that voted into cast (tiles,). COMPOSITE=True:
    rows (M, KP) per-splat features -> out (H*W, KP) their composite, best (H*W,) the most
    visible Gaussian and, with IMAGE, depth (H*W,) the weighted depth and trans (H*W,) the final
    T, each pixel ending at t_stop (the vote ends at eps, and counts within delta px where
    USE_DISTANCE). Whether any pixel is still live is asked every CHECK_EVERY splats (a block
    reduction; dead pixels do no work meanwhile). Reductions go through tl.reduce with Triton's
    own combine functions (its interpreter runs them as numpy reductions).

    Why one function: Triton inlines a jit helper, but a helper this kernel and the chunked
    vote shared (the 2DGS intersection and alpha) cost this kernel 7 registers and one block an
    SM on the 2DGS count rule under Triton 3.6, the GPU machines' version (63 against 56
    registers, 8 against 9 blocks; `python -m bench.speed.kernel_resources`), so the splat
    response is written out in both."""
    tile = tl.program_id(0)
    q = tl.arange(0, TILE * TILE)
    x0 = (tile % tiles_x) * TILE
    y0 = (tile // tiles_x) * TILE
    x = x0 + q % TILE
    y = y0 + q // TILE
    inside = (x < width) & (y < height)
    px = x.to(tl.float32) + 0.5
    py = y.to(tl.float32) + 0.5
    kk = tl.arange(0, KP)
    if COMPOSITE:
        feat = tl.zeros((TILE * TILE, KP), tl.float32)
        dacc = tl.zeros((TILE * TILE,), tl.float32)
        best_w = tl.zeros((TILE * TILE,), tl.float32)
        best = tl.full((TILE * TILE,), -1, tl.int64)
        live = inside
    else:
        lab = tl.load(pixel_labels_ptr + y * width + x, mask=inside, other=0)
        onehot = (lab[:, None] == kk[None, :]).to(tl.float32)
        live = inside & (eps < 1.0)
    T = tl.full((TILE * TILE,), 1.0, tl.float32)
    cast = tl.zeros((TILE * TILE,), tl.int32)
    start = tl.load(offsets_ptr + tile)
    n = tl.load(counts_ptr + tile)
    j = 0
    alive = tl.reduce(live.to(tl.int32), 0, tl.standard._elementwise_max) > 0
    while (j < n) & alive:
        s = tl.load(order_ptr + start + j)
        base = params_ptr + s * NP
        opac = tl.load(base + 2)
        dx = px - tl.load(base)
        dy = py - tl.load(base + 1)
        if SURFEL:  # projection.splat_response, 2DGS: ray-splat intersection
            m0 = tl.load(base + 4)
            m1 = tl.load(base + 5)
            m2 = tl.load(base + 6)
            m3 = tl.load(base + 7)
            m4 = tl.load(base + 8)
            m5 = tl.load(base + 9)
            m6 = tl.load(base + 10)
            m7 = tl.load(base + 11)
            m8 = tl.load(base + 12)
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
            depth = tl.where(use3d, u * m6 + v * m7 + m8, tl.load(base + 3))
            power = -0.5 * rho
            reach = (rho <= 9.0) & (depth > 1e-2)
        else:  # 3DGS: EWA conic
            depth = tl.load(base + 3)
            a = tl.load(base + 4)
            b = tl.load(base + 5)
            c = tl.load(base + 6)
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            reach = power >= -4.5
        alpha = tl.minimum(opac * tl.exp(power), 0.99)  # projection.ALPHA_MAX
        alpha = tl.where(reach & (alpha >= 0.00392156862745098), alpha, 0.0)  # ALPHA_MIN, 1/255
        hit = live & (alpha > 0)
        after = T * (1.0 - alpha)
        if COMPOSITE:  # rasterize's rule: a pixel ends at the splat that would take T under t_stop
            kept = hit & (after >= t_stop)
            w = tl.where(kept, alpha * T, 0.0)
            feat += w[:, None] * tl.load(rows_ptr + s * KP + kk)[None, :]
            if IMAGE:
                dacc += w * depth
            better = w > best_w
            best_w = tl.where(better, w, best_w)
            best = tl.where(better, tl.load(ids_ptr + s), best)
            T = tl.where(kept, after, T)
            live = live & (after >= t_stop)
        else:  # the vote: T_i > eps, alpha_i > 0 and, with the distance rule, |d| < delta
            vote = hit
            if USE_DISTANCE:
                vote = vote & (dx * dx + dy * dy < delta * delta)
            if WEIGHTED:  # noqa: SIM108 (a constexpr branch, compiled out)
                w = tl.where(vote, alpha * T, 0.0)
            else:
                w = vote.to(tl.float32)
            cast += vote.to(tl.int32)
            near = True
            if USE_DISTANCE:  # no pixel centre of the tile within delta: nothing to add
                mx = tl.load(base)
                my = tl.load(base + 1)
                near = (mx > x0 + 0.5 - delta) & (mx < x0 + TILE - 0.5 + delta)
                near = near & (my > y0 + 0.5 - delta) & (my < y0 + TILE - 0.5 + delta)
            if near:
                per_label = tl.reduce(w[:, None] * onehot, 0, tl.standard._sum_combine)
                tl.atomic_add(
                    out_ptr + tl.load(ids_ptr + s) * num_labels + kk,
                    per_label.to(tl.float64),
                    mask=(kk < num_labels) & (per_label > 0),
                )
            T = tl.where(hit, after, T)
            live = live & (eps < T)
        j += 1
        if j % CHECK_EVERY == 0:
            alive = tl.reduce(live.to(tl.int32), 0, tl.standard._elementwise_max) > 0
    if COMPOSITE:
        pixel = y * width + x
        tl.store(out_ptr + pixel[:, None] * KP + kk[None, :], feat, mask=inside[:, None])
        tl.store(best_ptr + pixel, best, mask=inside)
        if IMAGE:
            tl.store(depth_ptr + pixel, dacc, mask=inside)
            tl.store(trans_ptr + pixel, T, mask=inside)
    else:
        tl.store(cast_ptr + tile, tl.reduce(cast.to(tl.int64), 0, tl.standard._sum_combine))


# Splats walked between two checks of whether any pixel of the tile is still live.
CHECK_EVERY = 8


@dataclass
class TiledView:
    """One view's splats as the walk takes them (no grad): proj, their packed parameters
    params (M, P) float32, and the 16x16 tile lists order / offsets / counts of `bin_tiles`
    over the boxes where alpha can reach 1/255 (`projection.reach_boxes`)."""

    proj: ProjectedSplats
    params: torch.Tensor
    order: torch.Tensor
    offsets: torch.Tensor
    counts: torch.Tensor
    width: int
    height: int
    tiles_x: int
    tiles_y: int


def tile_view(
    gaussians: Gaussians, camera: Camera, near: float, with_colors: bool
) -> TiledView | None:
    """Project and bin one view for the walk with PyTorch's operators; None when nothing is on
    screen (`triton_prepare.tile_view_fused` makes the same with two Triton kernels)."""
    if (gaussians.device.type == "cuda") == INTERPRET:
        mode = "Triton's interpreter (CPU tensors)" if INTERPRET else "CUDA (CUDA tensors)"
        raise ValueError(
            f"the triton kernel was set up for {mode} when triton was first imported; got "
            f"{gaussians.device} tensors (without CUDA, import sagonline.render.triton_vote "
            f"before anything else imports triton, or set TRITON_INTERPRET=1)"
        )
    proj = project(gaussians, camera, near=near, with_colors=with_colors)
    if len(proj) == 0:
        return None
    proj = replace(proj, bbox=reach_boxes(proj))
    tiles_x, tiles_y = math.ceil(camera.width / TILE), math.ceil(camera.height / TILE)
    _, order, offsets, counts = bin_tiles(proj, tiles_x, tiles_y, TILE)
    params = proj.params().float().contiguous()
    return TiledView(
        proj, params, order, offsets, counts, camera.width, camera.height, tiles_x, tiles_y
    )


def walk(
    view: TiledView,
    out: torch.Tensor,  # [N, K] float64 histogram (vote), or [H*W, KP] composite
    num_labels: int,
    *,
    pixel_labels: torch.Tensor | None = None,  # [H, W] int32, the vote's mask
    rows: torch.Tensor | None = None,  # [M, KP] per-splat features, the composite's
    best: torch.Tensor | None = None,  # [H*W] int64, the most visible Gaussian
    depth: torch.Tensor | None = None,  # [H*W] weighted depth (image)
    trans: torch.Tensor | None = None,  # [H*W] final T (image)
    cast: torch.Tensor | None = None,  # [tiles] int64, pairs that voted per tile
    rule: VoteRule | None = None,
    t_stop: float = 0.0,
    image: bool = False,
) -> None:
    """One launch of `_walk_kernel` over the view's tiles: the vote with `rule` (pixel_labels,
    out the histogram, cast the pairs per tile), else the composite of `rows` (out, best and,
    with `image`, depth and trans). Buffers a mode does not use are passed as placeholders."""
    spare_f, spare_i = view.params, view.proj.ids
    vote = rule is not None
    _walk_kernel[(view.tiles_x * view.tiles_y,)](
        view.params,
        view.order,
        view.offsets,
        view.counts,
        view.proj.ids,
        spare_i if pixel_labels is None else pixel_labels,
        spare_f if rows is None else rows,
        out,
        spare_i if best is None else best,
        spare_f if depth is None else depth,
        spare_f if trans is None else trans,
        spare_i if cast is None else cast,
        view.width,
        view.height,
        view.tiles_x,
        num_labels,
        float(rule.eps) if vote else 1.0,
        float(rule.delta) if vote and rule.delta is not None else 0.0,
        float(t_stop),
        COMPOSITE=not vote,
        IMAGE=image,
        SURFEL=view.proj.kind == "2dgs",
        WEIGHTED=vote and rule.weighting == "blend",
        USE_DISTANCE=vote and rule.delta is not None,
        TILE=TILE,
        KP=out.shape[1] if not vote else max(2, triton.next_power_of_2(num_labels)),
        NP=view.params.shape[1],
        CHECK_EVERY=CHECK_EVERY,
    )


def vote_walk(
    view: TiledView,
    hist: torch.Tensor,  # [N, K] float64, added into
    pixel_labels: torch.Tensor,  # [H, W] int32
    cast: torch.Tensor,  # [tiles] int64, pairs that voted per tile
    rule: VoteRule,
) -> None:
    """The vote's launch of the splat walk (`walk` with a rule)."""
    walk(view, hist, hist.shape[1], pixel_labels=pixel_labels, cast=cast, rule=rule)


def vote_into(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [H, W] long, the view's mask
    hist: torch.Tensor,  # [N, K] float64, added into
    rule: VoteRule,
    *,
    launch=vote_walk,
    prepare=tile_view,
) -> int:
    """The op `render.vote.vote_into` as one fused Triton kernel: one view's votes under `rule`
    added into hist; returns the pairs that voted. `prepare(gaussians, camera, near,
    with_colors)` makes the view's tile lists (`tile_view`, or `triton_prepare`'s), and
    `launch(view, hist, pixel_labels, cast, rule)` runs the kernel: the splat walk, or
    `triton_vote_chunk.vote_chunks`."""
    with torch.no_grad():
        view = prepare(gaussians, camera, 0.01, with_colors=False)
        if view is None:
            return 0
        cast = torch.zeros(view.tiles_x * view.tiles_y, dtype=torch.int64, device=hist.device)
        launch(view, hist, labels.to(torch.int32).contiguous(), cast, rule)
        return int(cast.sum())
