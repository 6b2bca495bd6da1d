"""Tile-based Gaussian rasterizer in plain PyTorch (same code on CPU and CUDA), with a trace.

Pipeline for one view:
1. `project` culls and projects the Gaussians (M survive);
2. every splat is listed in each 8x8 tile its bounding box touches; the (tile, depth rank)
   keys are sorted once, so each tile holds its splats front to back;
3. tiles are processed in chunks, their depth lists in blocks of `block` splats: alpha for every
   (tile, splat, pixel) in the block, transmittance by a cumulative product carried across
   blocks, and colour/feature accumulation by batched matmul. A chunk stops early once every
   pixel's transmittance is spent.

Compositing follows the 3DGS reference: alpha clipped at 0.99, skipped below 1/255, and a
splat is composited only if the transmittance after it stays >= `t_stop` (1e-4); the first
splat that would break that ends the pixel.

The trace streams, per block, the (pixel, Gaussian) pairs met front to back with T_i (the
transmittance before the splat), alpha_i and the distance of the splat's projected centre from
the pixel centre, filtered as a `TraceRequest` asks (T_i > eps, the centre within
delta). A consumer reduces each `TraceChunk` as it
arrives (the consensus vote scatter-adds into a per-Gaussian histogram), so a frame never holds
all of its traces at once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from sagonline.render.projection import ProjectedSplats, depth_rank, project, splat_response
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

T_STOP = 1e-4


@dataclass
class TraceChunk:
    """A batch of traced (pixel, Gaussian) contributions, all shapes (E,).

    pixel: linear index y * width + x; gaussian: index into the scene's Gaussians;
    transmittance: T_i before the splat; alpha: alpha_i; distance: |projected centre - pixel
    centre| in pixels.
    """

    pixel: torch.Tensor
    gaussian: torch.Tensor
    transmittance: torch.Tensor
    alpha: torch.Tensor
    distance: torch.Tensor

    def __len__(self) -> int:
        return self.pixel.shape[0]


TraceConsumer = Callable[[TraceChunk], None]


@dataclass(frozen=True)
class TraceRequest:
    """Stream a render's trace to `consumer`: each (pixel, Gaussian) pair met front to back
    with T_i > eps and alpha_i > 0 (and, with `delta`, the splat's projected centre within
    that many pixels of the pixel centre; None: no distance rule). With `image=False` (the
    vote's pass) nothing is composited, each pixel stops once T <= eps, and the render returns
    None."""

    consumer: TraceConsumer
    eps: float
    delta: float | None = None
    image: bool = False

    def keeps(
        self,
        T_before: torch.Tensor,  # [P] transmittance before the splat
        alpha: torch.Tensor,  # [P]
        dist2: torch.Tensor,  # [P] squared distance of the splat's centre to the pixel's
    ) -> torch.Tensor:  # [P] bool
        """The pairs this request streams."""
        hit = (T_before > self.eps) & (alpha > 0)
        if self.delta is not None:
            hit &= dist2 < self.delta**2
        return hit


@dataclass
class RenderOutput:
    """rgb: (H, W, 3) linear colour over the background; alpha: (H, W) accumulated opacity;
    depth: (H, W) alpha-weighted camera depth (divide by alpha for the expected surface depth);
    features: (H, W, F) composited per-Gaussian attributes or None; ids: (H, W) index of the
    Gaussian with the largest blend weight (-1 where none) or None."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    features: torch.Tensor | None = None
    ids: torch.Tensor | None = None


def image_output(
    feat: torch.Tensor,  # [H, W, 3 + F] composited colour, then features
    final_T: torch.Tensor,  # [H, W]
    depth: torch.Tensor,  # [H, W]
    background: torch.Tensor | None,  # [3]
    with_features: bool,
    ids: torch.Tensor | None,  # [H, W]
) -> RenderOutput:
    """A walk's buffers as every renderer returns them: colour over the background
    (black by default), alpha = 1 - T, the features after the colour where asked for."""
    bg = torch.zeros(3, device=feat.device) if background is None else background.to(feat)
    return RenderOutput(
        rgb=feat[..., :3] + final_T[..., None] * bg,
        alpha=1.0 - final_T,
        depth=depth,
        features=feat[..., 3:] if with_features else None,
        ids=ids,
    )


@dataclass
class RasterStats:
    """Work counters of the last call: splat-tile intersections and Gaussian-pixel evaluations."""

    splats: int = 0
    intersections: int = 0
    evaluations: int = 0


def rasterize(
    gaussians: Gaussians,
    camera: Camera,
    *,
    background: torch.Tensor | None = None,  # [3]
    features: torch.Tensor | None = None,  # [N, F]
    return_ids: bool = False,
    trace: TraceRequest | None = None,
    t_stop: float = T_STOP,
    near: float = 0.01,
    tile_size: int = 8,
    block: int = 16,
    max_block: int = 128,
    max_elements: int = 1 << 21,
    stats: RasterStats | None = None,
) -> RenderOutput | None:
    """Render one view (and optionally stream its trace).

    gaussians: N splats; camera: the view; features: (N, F) attributes to composite alongside
    RGB (e.g. one-hot labels); background: (3,) colour, black by default; trace: what to stream
    (see `TraceRequest`; without its image, None is returned).

    Why one function: it is the readable twin of the compiled kernel, one pass over the tiles
    written straight through (project, bin, sort, composite, trace) so it can be read and
    checked against the kernel and the brute-force reference step for step.
    """
    device = gaussians.device
    trace_only = trace is not None and not trace.image
    W, H = camera.width, camera.height
    proj = project(gaussians, camera, near=near, with_colors=not trace_only)
    ts = tile_size
    ntx, nty = math.ceil(W / ts), math.ceil(H / ts)
    n_tiles, P = ntx * nty, ts * ts
    feat_dim = 0 if trace_only else 3 + (features.shape[1] if features is not None else 0)
    if not trace_only:
        feat_all = proj.colors
        if features is not None:
            feat_all = torch.cat([feat_all, features[proj.ids].to(feat_all.dtype)], dim=1)
    acc_feat = torch.zeros(n_tiles, P, feat_dim, device=device)
    acc_depth = torch.zeros(n_tiles, P, device=device)
    final_T = torch.ones(n_tiles, P, device=device)
    best_id = torch.full((n_tiles, P), -1, dtype=torch.long, device=device) if return_ids else None
    stop_T = trace.eps if trace_only else t_stop

    tile_ids, splat_order, tile_offsets, tile_counts = bin_tiles(proj, ntx, nty, ts)
    if stats is not None:
        stats.splats, stats.intersections, stats.evaluations = len(proj), splat_order.numel(), 0
    params = proj.params()
    local = torch.arange(P, device=device)
    lx, ly = (local % ts).float() + 0.5, (local // ts).float() + 0.5
    kind = proj.kind

    busy = torch.nonzero(tile_counts > 0).squeeze(1)
    busy = busy[torch.argsort(tile_counts[busy], descending=True)]
    start = 0
    while start < busy.numel():
        longest = int(tile_counts[busy[start]])
        widest = min(max_block, longest)  # chunk size fits the largest depth block
        n_chunk = max(1, min(busy.numel() - start, max_elements // (widest * P)))
        tiles = busy[start : start + n_chunk]
        start += n_chunk
        counts, offsets = tile_counts[tiles], tile_offsets[tiles]
        tx, ty = tiles % ntx, tiles // ntx
        px = (tx[:, None] * ts + lx[None, :]).unsqueeze(1)  # (T, 1, P)
        py = (ty[:, None] * ts + ly[None, :]).unsqueeze(1)
        pixel_in = (px < W) & (py < H)
        pixel_lin = (py.long() * W + px.long()).squeeze(1)  # (T, P)
        # T: true transmittance before the next splat; T_kept: product over composited splats.
        T = torch.where(pixel_in, 1.0, 0.0).to(px.dtype)  # padding pixels take no work
        T_kept = T.clone()
        feat_c = torch.zeros(tiles.numel(), P, feat_dim, device=device)
        depth_c = torch.zeros(tiles.numel(), P, device=device)
        if return_ids:
            best_w_c = torch.zeros(tiles.numel(), P, device=device)
            best_id_c = torch.full((tiles.numel(), P), -1, dtype=torch.long, device=device)
        rows = torch.arange(tiles.numel(), device=device)  # tiles still being composited
        b0, blk = 0, min(block, longest)
        while b0 < longest:
            # depth blocks double in size: opaque tiles finish in the first small blocks,
            # translucent ones (fresh fits, fog) are not walked in many tiny steps
            blk = min(blk, longest - b0)
            rows = rows[counts[rows] > b0]
            if rows.numel() == 0:
                break
            j = b0 + torch.arange(blk, device=device)
            cnt = counts[rows]
            in_list = j[None, :] < cnt[:, None]  # (R, B)
            pos = offsets[rows, None] + torch.minimum(j[None, :], cnt[:, None] - 1)
            splats = splat_order[pos]  # (R, B) indices into proj
            px_r, py_r = px[rows], py[rows]
            alpha, depth_px, dist2 = splat_response(kind, params[splats], px_r, py_r)
            alpha = alpha * in_list.unsqueeze(2)
            one_minus = 1.0 - alpha
            T_r = T[rows]
            T_before = T_r * torch.cumprod(
                torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], dim=1), dim=1
            )
            if stats is not None:
                stats.evaluations += alpha.numel()
            if trace is not None:
                hit = trace.keeps(T_before, alpha, dist2)
                t_i, b_i, p_i = torch.nonzero(hit, as_tuple=True)
                if t_i.numel():
                    trace.consumer(
                        TraceChunk(
                            pixel=pixel_lin[rows[t_i], p_i],
                            gaussian=proj.ids[splats[t_i, b_i]],
                            transmittance=T_before[t_i, b_i, p_i],
                            alpha=alpha[t_i, b_i, p_i],
                            distance=dist2[t_i, b_i, p_i].sqrt(),
                        )
                    )
            # T is monotone, so the first splat failing this test ends the pixel for good.
            keep = (T_before * one_minus >= stop_T) & (alpha > 0)
            if not trace_only:
                weight = torch.where(keep, alpha * T_before, 0.0)  # (R, B, P)
                feat_c[rows] += torch.bmm(weight.transpose(1, 2), feat_all[splats])
                depth_c[rows] += (weight * depth_px).sum(1)
                if return_ids:
                    w_max, arg = weight.max(dim=1)
                    better = w_max > best_w_c[rows]
                    best_w_c[rows] = torch.where(better, w_max, best_w_c[rows])
                    best_id_c[rows] = torch.where(
                        better, proj.ids[splats.gather(1, arg)], best_id_c[rows]
                    )
                T_kept[rows] = T_kept[rows] * torch.where(keep, one_minus, 1.0).prod(
                    dim=1, keepdim=True
                )
            T_r = T_before[:, -1:] * one_minus[:, -1:]
            T[rows] = T_r
            b0, blk = b0 + blk, min(2 * blk, max_block)
            # A tile is finished once no pixel could still composite a splat.
            rows = rows[(T_r * (1.0 - 1.0 / 255.0) >= stop_T).flatten(1).any(1)]
        acc_feat[tiles] = feat_c
        acc_depth[tiles] = depth_c
        final_T[tiles] = torch.where(pixel_in.squeeze(1), T_kept.squeeze(1), 1.0)
        if return_ids:
            best_id[tiles] = best_id_c
    if trace_only:
        return None

    return image_output(
        _untile(acc_feat, ntx, nty, ts, H, W),
        _untile(final_T[..., None], ntx, nty, ts, H, W)[..., 0],
        _untile(acc_depth[..., None], ntx, nty, ts, H, W)[..., 0],
        background,
        features is not None,
        _untile(best_id[..., None], ntx, nty, ts, H, W)[..., 0] if return_ids else None,
    )


def bin_tiles(proj: ProjectedSplats, ntx: int, nty: int, ts: int):
    """Sorted (tile, depth) lists: per-tile offsets/counts into `order` (indices into proj)."""
    device = proj.means2d.device
    m = len(proj)
    x0 = torch.floor(proj.bbox[:, 0] / ts).clamp(0, ntx).long()
    x1 = (torch.floor(proj.bbox[:, 1] / ts) + 1).clamp(0, ntx).long()
    y0 = torch.floor(proj.bbox[:, 2] / ts).clamp(0, nty).long()
    y1 = (torch.floor(proj.bbox[:, 3] / ts) + 1).clamp(0, nty).long()
    wx, wy = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    n = wx * wy
    # one host sync for the pairs' count (on CUDA each repeat_interleave without it is another)
    total = int(n.sum())
    splat = torch.repeat_interleave(torch.arange(m, device=device), n, output_size=total)
    first = (torch.cumsum(n, 0) - n)[splat]
    local = torch.arange(total, device=device) - first
    tx = x0[splat] + local % wx[splat]
    ty = y0[splat] + local // wx[splat]
    tile = ty * ntx + tx
    rank = depth_rank(proj)
    key = tile * max(m, 1) + rank[splat]
    key, perm = torch.sort(key)
    order = splat[perm]
    counts = torch.bincount(tile, minlength=ntx * nty)
    offsets = torch.cumsum(counts, 0) - counts
    return tile, order, offsets, counts


def _untile(x: torch.Tensor, ntx: int, nty: int, ts: int, H: int, W: int) -> torch.Tensor:
    """(tiles, ts*ts, C) -> (H, W, C)."""
    c = x.shape[-1]
    img = x.reshape(nty, ntx, ts, ts, c).permute(0, 2, 1, 3, 4).reshape(nty * ts, ntx * ts, c)
    return img[:H, :W]
