"""The compiled CPU rasterizer: `rasterize`'s compositing in C++ with a hand-written backward.

Same projection (`project`, autograd), same tile lists (`bin_tiles`'s, built by a counting sort
in C++), same compositing rules as the PyTorch path; the per-pixel walk and its gradient run in
one C++ loop per tile (csrc/raster_cpu.cpp, threads over tiles) instead of autograd over (tile,
splat, pixel) tensors. This is what makes CPU scene fitting practical. The extension is compiled
on first use (torch.utils.cpp_extension, needs a C++ compiler and ninja) and cached. It also
renders the most-visible Gaussian per pixel (`return_ids`). The vote's pass (`vote_into`, behind
`render.vote_histogram`), the label renders (`label_walk_native`) and groups of Gaussians'
alpha and depth, each group alone (`coverage_native`), walk a view prepared in C++
(`prepare_view`: projection without autograd, depth sort, tile lists; csrc/prepare_view.cpp); a
streamed trace (`rasterize(trace=...)`) is the PyTorch path's. `torch_on_one_thread` gives the
kernels their own thread count while torch's ops run on one (fits use it).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
from dataclasses import dataclass

import torch

from sagonline.render.kernels import NativeBuildError, load_extension
from sagonline.render.projection import project
from sagonline.render.rasterize import T_STOP, RenderOutput, image_output
from sagonline.render.rule import VoteRule
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

log = logging.getLogger(__name__)


@functools.cache
def native_available() -> bool:
    try:
        load_extension()
        return True
    except NativeBuildError as exc:
        log.warning("%s; using the PyTorch rasterizer", exc)
        return False


def bin_tiles(proj, ntx: int, nty: int, tile_size: int):
    """`rasterize.bin_tiles`'s (order, offsets, counts) by a counting sort in C++: the same
    lists in the same order, in O(splats + intersections) instead of a sort of every
    intersection."""
    by_depth = torch.sort(proj.depths.detach(), stable=True).indices
    return load_extension().bin_tiles(
        proj.bbox.detach().float().contiguous(), by_depth, ntx, nty, tile_size
    )


class _Composite(torch.autograd.Function):
    """(M, K) packed splat parameters, (M, C) colours, (M, 4) pixel bounding boxes of the
    3-sigma supports -> feat (H, W, C), depth (H, W), final transmittance (H, W); differentiable
    in params and colours."""

    @staticmethod
    def forward(
        ctx, params, colors, surfel, boxes, order, offsets, counts, width, height, tile, t_stop
    ):
        ext = load_extension()
        feat, depth, final_T, last, best = ext.forward(
            surfel, params, colors, boxes, order, offsets, counts, width, height, tile, t_stop
        )
        ctx.save_for_backward(params, colors, boxes, order, offsets, counts, final_T, last)
        ctx.settings = (surfel, width, height, tile)
        ctx.mark_non_differentiable(best)
        return feat, depth, final_T, best

    @staticmethod
    def backward(ctx, g_feat, g_depth, g_T, _g_best):
        params, colors, boxes, order, offsets, counts, final_T, last = ctx.saved_tensors
        surfel, width, height, tile = ctx.settings
        zeros = torch.zeros_like
        g_params, g_colors = load_extension().backward(
            surfel,
            params,
            colors,
            boxes,
            order,
            offsets,
            counts,
            width,
            height,
            tile,
            final_T,
            last,
            zeros(final_T)[..., None].expand(-1, -1, colors.shape[1]) if g_feat is None else g_feat,
            zeros(final_T) if g_depth is None else g_depth,
            zeros(final_T) if g_T is None else g_T,
        )
        return (g_params, g_colors) + (None,) * 9


def rasterize_native(
    gaussians: Gaussians,
    camera: Camera,
    *,
    background: torch.Tensor | None = None,  # [3]
    features: torch.Tensor | None = None,  # [N, F]
    t_stop: float = T_STOP,
    near: float = 0.01,
    tile_size: int = 8,
    return_ids: bool = False,
) -> RenderOutput:
    """Render one view on the CPU through the C++ kernel; outputs as `rasterize`, ids (the most
    visible Gaussian per pixel, -1 where none) with `return_ids`."""
    if gaussians.device.type != "cpu":
        raise ValueError("the native rasterizer runs on the CPU; use gsplat or torch on CUDA")
    W, H = camera.width, camera.height
    proj = project(gaussians, camera, near=near)
    ntx, nty = math.ceil(W / tile_size), math.ceil(H / tile_size)
    order, offsets, counts = bin_tiles(proj, ntx, nty, tile_size)
    colors = proj.colors
    if features is not None:
        colors = torch.cat([colors, features[proj.ids].to(colors.dtype)], dim=1)
    params = proj.params().float()
    feat, depth, final_T, best = _Composite.apply(
        params,
        colors.float(),
        proj.kind == "2dgs",
        proj.bbox.detach().float().contiguous(),
        order,
        offsets,
        counts,
        W,
        H,
        tile_size,
        float(t_stop),
    )
    ids = _gaussian_ids(best, proj.ids) if return_ids else None
    return image_output(feat, final_T, depth, background, features is not None, ids)


def _gaussian_ids(best: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """(H, W) projected-splat indices (-1: none) -> Gaussian indices (-1: none)."""
    if ids.numel() == 0:
        return best
    return torch.where(best >= 0, ids[best.clamp_min(0)], best)


@dataclass
class PreparedView:
    """One view's splats as the compiled passes take them (no autograd): ids (M,) Gaussian of
    each splat, params (M, 7 | 13) packed as `ProjectedSplats.params`, boxes (M, 4) bounding
    where alpha >= 1/255, spans (M, 4) int32 the pixels x0 <= x < x1, y0 <= y < y1 they cover,
    and the tile lists order / offsets / counts of `bin_tiles`."""

    surfel: bool
    ids: torch.Tensor
    params: torch.Tensor
    boxes: torch.Tensor
    spans: torch.Tensor
    order: torch.Tensor
    offsets: torch.Tensor
    counts: torch.Tensor


def prepare_view(
    gaussians: Gaussians, camera: Camera, *, near: float = 0.01, tile_size: int = 8
) -> PreparedView:
    """`project` (no grad, no colours), the depth sort and the tile lists in one C++ call."""
    if gaussians.device.type != "cpu":
        raise ValueError("the native kernels run on the CPU; use triton or gsplat on CUDA")
    g = gaussians

    def f32(t: torch.Tensor) -> torch.Tensor:
        return t.detach().float().contiguous()

    out = load_extension().prepare_view(
        g.kind == "2dgs",
        f32(g.means),
        f32(g.quats),
        f32(g.scales),
        f32(g.opacities),
        f32(camera.rotation),
        f32(camera.translation),
        f32(camera.K),
        camera.width,
        camera.height,
        float(near),
        tile_size,
    )
    return PreparedView(g.kind == "2dgs", *out)


def vote_into(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [H, W] long, the view's mask
    hist: torch.Tensor,  # [N, K] float64, added into
    rule: VoteRule,
) -> int:
    """The op `render.vote.vote_into` in C++ (csrc/prepare_view.cpp, csrc/vote_cpu.cpp): the
    pairs of its PyTorch reference under `rule`, added into hist; returns how many pairs
    voted."""
    view = prepare_view(gaussians, camera)
    return load_extension().vote(
        view.surfel,
        view.ids,
        view.params,
        view.spans,
        view.order,
        view.offsets,
        view.counts,
        camera.width,
        camera.height,
        8,
        labels.flatten().long(),
        hist.shape[1],
        float(rule.eps),
        None if rule.delta is None else float(rule.delta),
        rule.weighting == "blend",
        hist.view(-1),
    )


def walk_prepared(
    view: PreparedView,
    camera: Camera,
    channels: torch.Tensor,  # [M, C] per splat of the view, C may be 0
    t_stop: float = T_STOP,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:  # [H, W, C], 3x [H, W]
    """The compositing walk on a prepared view, no shading and no autograd: (H, W, C) the
    composited channels, (H, W) alpha-weighted depth, (H, W) final transmittance and (H, W)
    the most visible Gaussian (-1: none)."""
    feat, depth, final_T, _, best = load_extension().forward(
        view.surfel,
        view.params,
        channels.float().contiguous(),
        view.boxes,
        view.order,
        view.offsets,
        view.counts,
        camera.width,
        camera.height,
        8,
        float(t_stop),
    )
    return feat, depth, final_T, _gaussian_ids(best, view.ids)


def coverage_native(
    gaussians: Gaussians,
    camera: Camera,
    groups: torch.Tensor,  # [G, N] bool, G <= 8: the Gaussians of each group
    *,
    t_stop: float = T_STOP,
) -> tuple[torch.Tensor, torch.Tensor]:  # [G, H, W] alpha, [G, H, W] alpha-weighted depth
    """Each group of Gaussians drawn alone, `rasterize_native`'s alpha and depth without its
    colours: one unshaded walk (no SH, no autograd) over a `prepare_view` view of all the
    groups' Gaussians, each splat compositing into the groups it belongs to, each group with a
    transmittance of its own. The depth sort is stable, so a group's splats meet each pixel in
    the order a view of that group alone gives them."""
    if groups.ndim != 2 or groups.shape[1] != len(gaussians) or not 1 <= len(groups) <= 8:
        raise ValueError(f"groups must be (1..8, {len(gaussians)}) bool, got {tuple(groups.shape)}")
    groups = groups.to(device="cpu", dtype=torch.bool)
    union = groups.any(0)
    if not bool(union.any()):  # nothing to draw: no coverage, no depth
        empty = torch.zeros(len(groups), camera.height, camera.width)
        return empty, empty.clone()
    subset = gaussians if bool(union.all()) else gaussians.subset(union)
    view = prepare_view(subset, camera)
    weights = 1 << torch.arange(len(groups), dtype=torch.int64)
    bits = (groups[:, union].long() * weights[:, None]).sum(0).to(torch.uint8)
    depth, final_t = load_extension().coverage(
        view.surfel,
        view.params,
        view.boxes,
        view.order,
        view.offsets,
        view.counts,
        bits[view.ids].contiguous(),
        len(groups),
        camera.width,
        camera.height,
        8,
        float(t_stop),
    )
    return 1.0 - final_t, depth


def surface_native(
    gaussians: Gaussians, camera: Camera, *, t_stop: float = T_STOP
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # [H, W] alpha, depth, ids
    """The whole scene in one view, unshaded: (H, W) alpha, alpha-weighted depth and the most
    visible Gaussian (-1: none), by the walk of the label renders and the coverage (a
    `prepare_view` view, no SH, no autograd), whose alpha, depth and ids are the same whatever
    channels it composites: a label render's (`label_walk_native`) are these."""
    view = prepare_view(gaussians, camera)
    _, depth, final_t, ids = walk_prepared(view, camera, torch.zeros(len(view.ids), 0), t_stop)
    return 1.0 - final_t, depth, ids


def label_walk_native(
    gaussians: Gaussians,
    camera: Camera,
    splat_labels: torch.Tensor,  # [N] long, -1 none
    num_labels: int,
    *,
    with_weights: bool = True,
    t_stop: float = T_STOP,
) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor, torch.Tensor]:  # [H, W, K], 3x [H, W]
    """The label renders' walk in C++ on a `prepare_view` view (no SH, no autograd): (H, W, K)
    composited one-hot weights of the Gaussians whose label (splat_labels (N,), -1: none) is
    >= 0 (None without `with_weights`), and the view's surface, `surface_native`'s: (H, W)
    most visible Gaussians (-1: none), alpha and alpha-weighted depth."""
    view = prepare_view(gaussians, camera)
    k = num_labels if with_weights else 0
    lab = splat_labels[view.ids].long()
    onehot = torch.zeros(len(view.ids), k)
    if k and len(view.ids):
        known = lab >= 0
        onehot[known.nonzero().squeeze(1), lab[known]] = 1.0
    feat, depth, final_t, ids = walk_prepared(view, camera, onehot, t_stop)
    return (feat if with_weights else None), ids, 1.0 - final_t, depth


@contextlib.contextmanager
def torch_on_one_thread():
    """Run torch's own CPU ops on one thread and the compiled kernels on all of torch's threads.
    torch splits an elementwise op over threads in chunks whose vectorised and scalar tails round
    exp or sigmoid differently, and a reduction's order with them: one thread makes those
    results the same on any machine's thread count, while the kernels, which do most of a fit's
    work, keep every thread (their sums do not depend on the count)."""
    threads = torch.get_num_threads()
    ext = load_extension() if native_available() else None
    if ext is not None:
        ext.set_kernel_threads(threads)
    torch.set_num_threads(1)
    try:
        yield threads
    finally:
        torch.set_num_threads(threads)
        if ext is not None:
            ext.set_kernel_threads(0)


def vote_simd() -> str:
    """The instruction set the compiled vote walks with: 'avx2' or 'generic'."""
    return load_extension().vote_simd()


__all__ = [
    "NativeBuildError",
    "load_extension",
    "native_available",
    "coverage_native",
    "label_walk_native",
    "rasterize_native",
    "surface_native",
    "PreparedView",
    "prepare_view",
    "vote_into",
    "vote_simd",
    "walk_prepared",
]
