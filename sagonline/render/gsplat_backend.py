"""gsplat on CUDA behind the same interface as `rasterize` (images and streamed traces).

Images come from `gsplat.rasterization` / `rasterization_2dgs` with colours evaluated here (SH
plus any extra feature channels) so both backends shade identically. The trace walks gsplat's
own tile intersections with `rasterize_to_indices_in_range(_2dgs)` in depth batches; alphas of
the returned (Gaussian, pixel) pairs are evaluated with this library's `splat_response`, so the
vote sees the same alpha and distance definitions on every backend. gsplat's support rule
(radius from the largest eigenvalue, per tile) decides which pairs are visited; pairs outside
the 3-sigma ellipse get alpha 0 from `splat_response` and are dropped.

gsplat's rasterizer is CUDA-only: on CPU use the torch backend.
"""

from __future__ import annotations

import torch

from sagonline.render.projection import depth_rank, project, splat_response, view_colors
from sagonline.render.rasterize import RenderOutput, TraceChunk, TraceRequest
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians


def gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


def surfel_scales(
    scales: torch.Tensor,  # [N, 2]
) -> torch.Tensor:  # [N, 3]
    """(N, 2) surfel scales -> the (N, 3) gsplat's 2DGS functions take (the third axis, the
    normal, is never used by them: their ray transform keeps the first two columns of R S)."""
    return torch.cat([scales, torch.zeros_like(scales[:, :1])], dim=1)


def _require_gsplat():
    try:
        import gsplat
    except ImportError as exc:
        raise RuntimeError(
            "renderer backend 'gsplat' needs the gsplat package: "
            "pip install -e '.[gsplat]' (CUDA only)"
        ) from exc
    if not torch.cuda.is_available():
        raise RuntimeError("renderer backend 'gsplat' needs CUDA; use backend 'torch' on CPU")
    return gsplat


def rasterize_gsplat(
    gaussians: Gaussians,
    camera: Camera,
    *,
    background=None,
    features=None,
    trace: TraceRequest | None = None,
    near: float = 0.01,
    tile_size: int = 16,
    batch: int = 32,
) -> RenderOutput | None:
    """Same contract as `sagonline.render.rasterize` (ids are not produced by this backend)."""
    gsplat = _require_gsplat()
    trace_only = trace is not None and not trace.image
    g = gaussians
    cam = camera.to(g.device)
    viewmats, Ks = cam.world_to_cam[None], cam.K[None]
    # every Gaussian shaded (gsplat culls what it does not draw): no projection of ours, and
    # no wait on the GPU for its cull, unless a trace needs the projected splats
    if trace_only:
        colors = torch.zeros(len(g), 1, device=g.device)
    else:
        colors = view_colors(g, None, cam.center)
        if features is not None:
            colors = torch.cat([colors, features.to(colors)], dim=1)
    common = dict(
        viewmats=viewmats,
        Ks=Ks,
        width=cam.width,
        height=cam.height,
        near_plane=near,
        packed=False,
        tile_size=tile_size,
        render_mode="RGB+D",
    )
    if g.kind == "3dgs":
        img, alphas, meta = gsplat.rasterization(
            g.means, g.quats, g.scales, g.opacities, colors, **common
        )
        shape_key, indices_fn = "conics", gsplat.rasterize_to_indices_in_range
    else:
        # rasterization_2dgs takes per-camera colours only: (C, N, D)
        img, alphas, *_, meta = gsplat.rasterization_2dgs(
            g.means, g.quats, surfel_scales(g.scales), g.opacities, colors[None], **common
        )
        shape_key, indices_fn = "ray_transforms", gsplat.rasterize_to_indices_in_range_2dgs
    if trace is not None:
        _walk_trace(
            indices_fn,
            meta,
            shape_key,
            project(g, cam, near=near, with_colors=False),
            len(g),
            cam,
            trace,
            tile_size,
            batch,
        )
    if trace_only:
        return None
    img, alpha = img[0], alphas[0, ..., 0]
    bg = torch.zeros(3, device=g.device) if background is None else background.to(g.device)
    rgb = img[..., :3] + (1 - alpha)[..., None] * bg
    return RenderOutput(
        rgb=rgb,
        alpha=alpha,
        depth=img[..., -1],
        features=img[..., 3:-1] if features is not None else None,
    )


def _walk_trace(indices_fn, meta, shape_key, proj, n, cam, request, tile_size, batch):
    W, H = cam.width, cam.height
    device = proj.means2d.device
    local = torch.full((n,), -1, dtype=torch.long, device=device)
    local[proj.ids] = torch.arange(len(proj), device=device)
    params = proj.params()
    rank = depth_rank(proj)
    T = torch.ones(1, H, W, device=device)
    offsets = meta["isect_offsets"]
    longest = int(
        torch.diff(
            torch.cat([offsets.flatten(), offsets.new_tensor([meta["flatten_ids"].numel()])])
        ).max()
    )
    for start in range(0, longest, batch):
        gids, pids, _ = indices_fn(
            start,
            start + batch,
            T,
            meta["means2d"],
            meta[shape_key],
            meta["opacities"],
            W,
            H,
            tile_size,
            offsets,
            meta["flatten_ids"],
        )
        if gids.numel() == 0:
            break
        chunk, T_flat = trace_step(
            gids, pids, T.view(-1), local, rank, params, proj.kind, W, request
        )
        T = T_flat.view(1, H, W)
        if len(chunk):
            request.consumer(chunk)


def trace_step(
    gids: torch.Tensor,  # [E] Gaussian ids
    pids: torch.Tensor,  # [E] pixel ids
    T: torch.Tensor,  # [H * W] transmittance before
    local: torch.Tensor,  # [E]
    rank: torch.Tensor,  # [E] depth rank
    params: torch.Tensor,  # [M, P] packed splats
    kind: str,
    width: int,
    request: TraceRequest,
) -> tuple[TraceChunk, torch.Tensor]:  # chunk, [H * W] transmittance after
    """One depth batch of (Gaussian, pixel) pairs -> the traced chunk and the updated T.

    gids/pids: (E,) original Gaussian ids and linear pixel ids in any order; T: (H*W,)
    transmittance before this batch. Pairs are ordered front to back per pixel, alphas evaluated
    with `splat_response`, and T_i = T[pixel] * prod of (1 - alpha) of the pixel's earlier pairs.
    """
    li = local[gids]
    ok = li >= 0
    gids, pids, li = gids[ok], pids[ok], li[ok]
    order = torch.argsort(pids * (rank.numel() + 1) + rank[li])
    gids, pids, li = gids[order], pids[order], li[order]
    px = (pids % width).to(params.dtype) + 0.5
    py = (pids // width).to(params.dtype) + 0.5
    alpha, _, dist2 = splat_response(
        kind, params[li][:, None, :], px[:, None, None], py[:, None, None]
    )
    alpha, dist2 = alpha[:, 0, 0], dist2[:, 0, 0]
    log_keep = torch.log1p(-alpha.double())
    csum = torch.cumsum(log_keep, 0)
    first = torch.ones_like(pids, dtype=torch.bool)
    first[1:] = pids[1:] != pids[:-1]
    seg_start = torch.cummax(
        torch.where(first, torch.arange(len(pids), device=pids.device), 0), 0
    ).values
    exclusive = csum - log_keep - (csum[seg_start] - log_keep[seg_start])
    T_before = (T[pids].double() * torch.exp(exclusive)).to(alpha.dtype)
    hit = request.keeps(T_before, alpha, dist2)
    T_new = T.clone()
    T_new.scatter_reduce_(0, pids, (1.0 - alpha).to(T.dtype), "prod")
    chunk = TraceChunk(
        pixel=pids[hit],
        gaussian=gids[hit],
        transmittance=T_before[hit],
        alpha=alpha[hit],
        distance=dist2[hit].sqrt(),
    )
    return chunk, T_new
