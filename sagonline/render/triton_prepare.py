"""A view's projection and tile lists in two Triton kernels: what `triton_vote.tile_view` makes
with PyTorch (`projection.project`, `projection.reach_boxes`, `rasterize.bin_tiles`), for the
Triton walks (the vote and the composite).

PyTorch's is about a hundred small operators per view, each a launch on a GPU: 3.5 of a vote's
6-7 ms on an H100 (docs/performance.md). Here:
1. `_project_kernel`, a program per BLOCK Gaussians: camera-space centre, the 3DGS conic or the
   2DGS transform, culling (behind `near`, degenerate, off screen, alpha never 1/255), the box
   where alpha can reach 1/255 and the 16x16 tiles it covers;
2. the culled Gaussians' indices (one host sync) and their tile counts' prefix sum (another);
3. `_emit_kernel`: each splat writes its (tile, depth) keys, tile in the high 32 bits and the
   depth's float32 bits (positive, so ordered as integers) in the low ones;
4. one stable sort of the keys (ties in projection order, as `bin_tiles`), and each tile's
   first pair by a binary search.

The formulas of `projection.py` in float32 (a last bit may round otherwise). Chosen by
SAGONLINE_TRITON_PREPARE (`backends.triton_prepare`): the default where CUDA is (an H200 made
a vote's lists in 0.9-1.1 ms against PyTorch's 3.1-3.5 ms), PyTorch's on the CPU.
"""

from __future__ import annotations

import math

import torch

# triton_vote first: without CUDA it chooses Triton's interpreter before triton is imported
from sagonline.render.triton_vote import TILE, TiledView, _kernel, tile_view

# isort: split
import triton
import triton.language as tl

from sagonline.render.backends import triton_prepare
from sagonline.render.projection import (
    ALPHA_MIN,
    LOW_PASS,
    SIGMA_CUTOFF,
    SURFEL_FILTER_INV_SQ,
    ProjectedSplats,
    view_colors,
)
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

# projection.py's constants as a compiled kernel may read a global: constexpr
_ALPHA_MIN = tl.constexpr(ALPHA_MIN)
_LOW_PASS = tl.constexpr(LOW_PASS)
_CUTOFF = tl.constexpr(SIGMA_CUTOFF)
_CUTOFF_SQ = tl.constexpr(SIGMA_CUTOFF**2)
_FILTER_RADIUS = tl.constexpr(SIGMA_CUTOFF / SURFEL_FILTER_INV_SQ**0.5)
_FILTER_INV_SQ = tl.constexpr(SURFEL_FILTER_INV_SQ)

# Gaussians per program of the projection, splats and tiles per step of the emission.
PROJECT_BLOCK = 256
EMIT_SPLATS = 64
EMIT_TILES = 16


@_kernel
def _project_kernel(
    means_ptr,
    quats_ptr,
    scales_ptr,
    opac_ptr,
    cam_ptr,
    params_ptr,
    boxes_ptr,
    rects_ptr,
    valid_ptr,
    n,
    width,
    height,
    tiles_x,
    tiles_y,
    near,
    SURFEL: tl.constexpr,
    NP: tl.constexpr,
    TILE: tl.constexpr,
    BLOCK: tl.constexpr,
):
    """BLOCK Gaussians: params (N, NP) as `ProjectedSplats.params` (mx, my, opacity, depth,
    then the conic a, b, c or the 2DGS transform row by row), boxes (N, 4) where alpha can
    reach 1/255 (`projection.reach_boxes`), rects (N, 4) int32 their tiles x0, y0, columns and
    count (0 when culled), valid (N,) int8 whether it survives culling (`projection.project`).
    cam (25,): R (9), t (3), K (9), the 3DGS Jacobian's limits -x, +x, -y, +y (4).

    Why one function: it is one GPU launch per view, which is the point; the two kinds'
    formulas are its two constexpr branches, and each is written out beside its PyTorch twin's
    name in projection.py so the two read line against line."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < n
    mx = tl.load(means_ptr + 3 * i, mask=m, other=0.0)
    my = tl.load(means_ptr + 3 * i + 1, mask=m, other=0.0)
    mz = tl.load(means_ptr + 3 * i + 2, mask=m, other=0.0)
    r00, r01, r02 = tl.load(cam_ptr), tl.load(cam_ptr + 1), tl.load(cam_ptr + 2)
    r10, r11, r12 = tl.load(cam_ptr + 3), tl.load(cam_ptr + 4), tl.load(cam_ptr + 5)
    r20, r21, r22 = tl.load(cam_ptr + 6), tl.load(cam_ptr + 7), tl.load(cam_ptr + 8)
    px = r00 * mx + r01 * my + r02 * mz + tl.load(cam_ptr + 9)
    py = r10 * mx + r11 * my + r12 * mz + tl.load(cam_ptr + 10)
    pz = r20 * mx + r21 * my + r22 * mz + tl.load(cam_ptr + 11)
    qw = tl.load(quats_ptr + 4 * i, mask=m, other=1.0)
    qx = tl.load(quats_ptr + 4 * i + 1, mask=m, other=0.0)
    qy = tl.load(quats_ptr + 4 * i + 2, mask=m, other=0.0)
    qz = tl.load(quats_ptr + 4 * i + 3, mask=m, other=0.0)
    # the Gaussian's rotation (scene.gaussians.quat_to_rotmat): its columns are the local axes
    g00 = 1 - 2 * (qy * qy + qz * qz)
    g01 = 2 * (qx * qy - qw * qz)
    g02 = 2 * (qx * qz + qw * qy)
    g10 = 2 * (qx * qy + qw * qz)
    g11 = 1 - 2 * (qx * qx + qz * qz)
    g12 = 2 * (qy * qz - qw * qx)
    g20 = 2 * (qx * qz - qw * qy)
    g21 = 2 * (qy * qz + qw * qx)
    g22 = 1 - 2 * (qx * qx + qy * qy)
    # C = R G: the Gaussian's axes (columns) in the camera's frame, before its scales
    c00 = r00 * g00 + r01 * g10 + r02 * g20
    c10 = r10 * g00 + r11 * g10 + r12 * g20
    c20 = r20 * g00 + r21 * g10 + r22 * g20
    c01 = r00 * g01 + r01 * g11 + r02 * g21
    c11 = r10 * g01 + r11 * g11 + r12 * g21
    c21 = r20 * g01 + r21 * g11 + r22 * g21
    c02 = r00 * g02 + r01 * g12 + r02 * g22
    c12 = r10 * g02 + r11 * g12 + r12 * g22
    c22 = r20 * g02 + r21 * g12 + r22 * g22
    opac = tl.load(opac_ptr + i, mask=m, other=0.0)
    k00, k01, k02 = tl.load(cam_ptr + 12), tl.load(cam_ptr + 13), tl.load(cam_ptr + 14)
    k10, k11, k12 = tl.load(cam_ptr + 15), tl.load(cam_ptr + 16), tl.load(cam_ptr + 17)
    k20, k21, k22 = tl.load(cam_ptr + 18), tl.load(cam_ptr + 19), tl.load(cam_ptr + 20)
    # alpha reaches 1/255 within Mahalanobis radius^2 r2 (projection.reach_boxes; 0: culled)
    r2 = 2.0 * tl.log(tl.maximum(opac, 1e-30) / _ALPHA_MIN) + 2e-3
    r2 = tl.minimum(tl.maximum(r2, 0.0), _CUTOFF_SQ)
    row = params_ptr + i * NP
    if SURFEL:  # projection._project_surfels: M = K [R t_u s_u | R t_v s_v | p_cam]
        s0 = tl.load(scales_ptr + 2 * i, mask=m, other=1.0)
        s1 = tl.load(scales_ptr + 2 * i + 1, mask=m, other=1.0)
        t00 = (k00 * c00 + k01 * c10 + k02 * c20) * s0
        t10 = (k10 * c00 + k11 * c10 + k12 * c20) * s0
        t20 = (k20 * c00 + k21 * c10 + k22 * c20) * s0
        t01 = (k00 * c01 + k01 * c11 + k02 * c21) * s1
        t11 = (k10 * c01 + k11 * c11 + k12 * c21) * s1
        t21 = (k20 * c01 + k21 * c11 + k22 * c21) * s1
        t02 = k00 * px + k01 * py + k02 * pz
        t12 = k10 * px + k11 * py + k12 * pz
        t22 = k20 * px + k21 * py + k22 * pz
        w = tl.maximum(t22, 1e-6)
        cx = t02 / w
        cy = t12 / w
        # the 3-sigma disc's image through its dual conic D = M diag(9, 9, -1) M^T
        d00 = _CUTOFF_SQ * (t00 * t00 + t01 * t01) - t02 * t02
        d11 = _CUTOFF_SQ * (t10 * t10 + t11 * t11) - t12 * t12
        d22 = _CUTOFF_SQ * (t20 * t20 + t21 * t21) - t22 * t22
        d02 = _CUTOFF_SQ * (t00 * t20 + t01 * t21) - t02 * t22
        d12 = _CUTOFF_SQ * (t10 * t20 + t11 * t21) - t12 * t22
        valid = d22 < 0
        d22s = tl.where(valid, d22, -1.0)
        hx = tl.sqrt(tl.maximum(d02 * d02 - d00 * d22, 0.0)) / tl.abs(d22s)
        hy = tl.sqrt(tl.maximum(d12 * d12 - d11 * d22, 0.0)) / tl.abs(d22s)
        rf = _FILTER_RADIUS
        bx0 = tl.minimum(d02 / d22s - hx, cx - rf)
        bx1 = tl.maximum(d02 / d22s + hx, cx + rf)
        by0 = tl.minimum(d12 / d22s - hy, cy - rf)
        by1 = tl.maximum(d12 / d22s + hy, cy + rf)
        # the same with r2 for 9 (a smaller disc keeps d22 < 0)
        e00 = r2 * (t00 * t00 + t01 * t01) - t02 * t02
        e11 = r2 * (t10 * t10 + t11 * t11) - t12 * t12
        e22 = tl.where(valid, r2 * (t20 * t20 + t21 * t21) - t22 * t22, -1.0)
        e02 = r2 * (t00 * t20 + t01 * t21) - t02 * t22
        e12 = r2 * (t10 * t20 + t11 * t21) - t12 * t22
        ex = tl.sqrt(tl.maximum(e02 * e02 - e00 * e22, 0.0)) / tl.abs(e22)
        ey = tl.sqrt(tl.maximum(e12 * e12 - e11 * e22, 0.0)) / tl.abs(e22)
        rr = tl.sqrt(r2 / _FILTER_INV_SQ)
        rx0 = tl.minimum(e02 / e22 - ex, cx - rr)
        rx1 = tl.maximum(e02 / e22 + ex, cx + rr)
        ry0 = tl.minimum(e12 / e22 - ey, cy - rr)
        ry1 = tl.maximum(e12 / e22 + ey, cy + rr)
        tl.store(row + 4, t00, mask=m)
        tl.store(row + 5, t01, mask=m)
        tl.store(row + 6, t02, mask=m)
        tl.store(row + 7, t10, mask=m)
        tl.store(row + 8, t11, mask=m)
        tl.store(row + 9, t12, mask=m)
        tl.store(row + 10, t20, mask=m)
        tl.store(row + 11, t21, mask=m)
        tl.store(row + 12, t22, mask=m)
    else:  # projection._project_ellipsoids: EWA, cov2d = (J C S)(J C S)^T + low-pass
        s0 = tl.load(scales_ptr + 3 * i, mask=m, other=1.0)
        s1 = tl.load(scales_ptr + 3 * i + 1, mask=m, other=1.0)
        s2 = tl.load(scales_ptr + 3 * i + 2, mask=m, other=1.0)
        fx, fy, ppx, ppy = k00, k11, k02, k12
        z = tl.maximum(pz, 1e-6)
        tx = tl.minimum(tl.maximum(px / z, -tl.load(cam_ptr + 21)), tl.load(cam_ptr + 22)) * z
        ty = tl.minimum(tl.maximum(py / z, -tl.load(cam_ptr + 23)), tl.load(cam_ptr + 24)) * z
        j00 = fx / z
        j02 = -fx * tx / (z * z)
        j11 = fy / z
        j12 = -fy * ty / (z * z)
        # the rows of J C S, whose product with itself is cov2d before the low-pass
        a0 = (j00 * c00 + j02 * c20) * s0
        a1 = (j00 * c01 + j02 * c21) * s1
        a2 = (j00 * c02 + j02 * c22) * s2
        b0 = (j11 * c10 + j12 * c20) * s0
        b1 = (j11 * c11 + j12 * c21) * s1
        b2 = (j11 * c12 + j12 * c22) * s2
        ca = a0 * a0 + a1 * a1 + a2 * a2 + _LOW_PASS
        cb = a0 * b0 + a1 * b1 + a2 * b2
        cc = b0 * b0 + b1 * b1 + b2 * b2 + _LOW_PASS
        det = ca * cc - cb * cb
        valid = det > 0
        det = tl.where(valid, det, 1.0)
        cx = fx * px / z + ppx
        cy = fy * py / z + ppy
        ext_x = _CUTOFF * tl.sqrt(tl.maximum(ca, 0.0))
        ext_y = _CUTOFF * tl.sqrt(tl.maximum(cc, 0.0))
        bx0 = cx - ext_x
        bx1 = cx + ext_x
        by0 = cy - ext_y
        by1 = cy + ext_y
        shrink = tl.sqrt(r2 / _CUTOFF_SQ)
        half_x = 0.5 * (bx1 - bx0) * shrink
        half_y = 0.5 * (by1 - by0) * shrink
        rx0 = cx - half_x
        rx1 = cx + half_x
        ry0 = cy - half_y
        ry1 = cy + half_y
        tl.store(row + 4, cc / det, mask=m)
        tl.store(row + 5, -cb / det, mask=m)
        tl.store(row + 6, ca / det, mask=m)
    finite = (tl.abs(bx0) < float("inf")) & (tl.abs(bx1) < float("inf"))
    finite = finite & (tl.abs(by0) < float("inf")) & (tl.abs(by1) < float("inf"))
    on_screen = (bx1 > 0) & (bx0 < width) & (by1 > 0) & (by0 < height)
    valid = m & valid & finite & (pz > near) & on_screen & (opac >= _ALPHA_MIN)
    # the tiles of the reach box (rasterize.bin_tiles), none for a culled Gaussian
    rx0 = tl.where(valid, rx0, 0.0)
    rx1 = tl.where(valid, rx1, 0.0)
    ry0 = tl.where(valid, ry0, 0.0)
    ry1 = tl.where(valid, ry1, 0.0)
    x0 = tl.minimum(tl.maximum(tl.floor(rx0 / TILE), 0.0), tiles_x * 1.0).to(tl.int32)
    x1 = tl.minimum(tl.maximum(tl.floor(rx1 / TILE) + 1.0, 0.0), tiles_x * 1.0).to(tl.int32)
    y0 = tl.minimum(tl.maximum(tl.floor(ry0 / TILE), 0.0), tiles_y * 1.0).to(tl.int32)
    y1 = tl.minimum(tl.maximum(tl.floor(ry1 / TILE) + 1.0, 0.0), tiles_y * 1.0).to(tl.int32)
    cols = tl.maximum(x1 - x0, 0)
    count = tl.where(valid, cols * tl.maximum(y1 - y0, 0), 0)
    tl.store(row, cx, mask=m)
    tl.store(row + 1, cy, mask=m)
    tl.store(row + 2, opac, mask=m)
    tl.store(row + 3, pz, mask=m)
    tl.store(boxes_ptr + 4 * i, rx0, mask=m)
    tl.store(boxes_ptr + 4 * i + 1, rx1, mask=m)
    tl.store(boxes_ptr + 4 * i + 2, ry0, mask=m)
    tl.store(boxes_ptr + 4 * i + 3, ry1, mask=m)
    tl.store(rects_ptr + 4 * i, x0, mask=m)
    tl.store(rects_ptr + 4 * i + 1, y0, mask=m)
    tl.store(rects_ptr + 4 * i + 2, cols, mask=m)
    tl.store(rects_ptr + 4 * i + 3, count, mask=m)
    tl.store(valid_ptr + i, valid.to(tl.int8), mask=m)


@_kernel
def _emit_kernel(
    rects_ptr,
    starts_ptr,
    depths_ptr,
    keys_ptr,
    splats_ptr,
    m,
    tiles_x,
    SPLATS: tl.constexpr,
    TILES: tl.constexpr,
):
    """SPLATS splats write their pairs from starts (M,): keys (P,) int64, the tile in the high
    32 bits and the depth's float32 bits in the low, and splats (P,) int64 the splat's index;
    rects (M, 4) int32 x0, y0, columns, count; depths (M,) float32, positive."""
    s = tl.program_id(0) * SPLATS + tl.arange(0, SPLATS)
    ms = s < m
    x0 = tl.load(rects_ptr + 4 * s, mask=ms, other=0)
    y0 = tl.load(rects_ptr + 4 * s + 1, mask=ms, other=0)
    cols = tl.maximum(tl.load(rects_ptr + 4 * s + 2, mask=ms, other=1), 1)
    count = tl.load(rects_ptr + 4 * s + 3, mask=ms, other=0)
    start = tl.load(starts_ptr + s, mask=ms, other=0)
    bits = tl.load(depths_ptr + s, mask=ms, other=1.0).to(tl.int32, bitcast=True).to(tl.int64)
    most = tl.reduce(count, 0, tl.standard._elementwise_max)
    k = tl.arange(0, TILES)[None, :]
    k0 = 0
    while k0 < most:
        kk = k0 + k
        take = kk < count[:, None]
        tx = x0[:, None] + kk % cols[:, None]
        ty = y0[:, None] + kk // cols[:, None]
        key = ((ty * tiles_x + tx).to(tl.int64) << 32) | bits[:, None]
        at = start[:, None] + kk
        tl.store(keys_ptr + at, key, mask=take)
        tl.store(splats_ptr + at, s.to(tl.int64)[:, None] + 0 * kk, mask=take)
        k0 += TILES


def _camera_row(camera: Camera) -> torch.Tensor:  # [25] float32
    """R (9), t (3), K (9) and the 3DGS Jacobian's clamp limits (4), as `_project_kernel`
    reads them (projection._project_ellipsoids: 1.3x the view frustum). Made where the camera
    is, in float64 as before (the same values): reading K and the pose on the host made each
    vote wait for the GPU twice."""
    K, pose = camera.K.detach().double(), camera.world_to_cam.detach().double()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = camera.width, camera.height
    gx, gy = 0.3 * w / (2 * fx), 0.3 * h / (2 * fy)  # the frustum's 0.3 margin
    limits = torch.stack([cx / fx + gx, (w - cx) / fx + gx, cy / fy + gy, (h - cy) / fy + gy])
    return torch.cat([pose[:3, :3].flatten(), pose[:3, 3], K.flatten(), limits]).float()


def tile_view_fused(
    gaussians: Gaussians, camera: Camera, near: float, with_colors: bool
) -> TiledView | None:
    """`triton_vote.tile_view` by the two kernels: the same splats (ids ascending), packed
    parameters, reach boxes and tile lists (within a last bit of float32); None when nothing is
    on screen. No gradients."""
    g, device = gaussians, gaussians.device
    n = len(g)
    surfel = g.kind == "2dgs"
    num_params = 13 if surfel else 7
    tiles_x, tiles_y = math.ceil(camera.width / TILE), math.ceil(camera.height / TILE)
    params = torch.empty(n, num_params, device=device)
    boxes = torch.empty(n, 4, device=device)
    rects = torch.empty(n, 4, dtype=torch.int32, device=device)
    valid = torch.empty(n, dtype=torch.int8, device=device)
    if n > 0:
        _project_kernel[(triton.cdiv(n, PROJECT_BLOCK),)](
            *(t.detach().float().contiguous() for t in (g.means, g.quats, g.scales, g.opacities)),
            _camera_row(camera).to(device),
            params,
            boxes,
            rects,
            valid,
            n,
            camera.width,
            camera.height,
            tiles_x,
            tiles_y,
            float(near),
            SURFEL=surfel,
            NP=num_params,
            TILE=TILE,
            BLOCK=PROJECT_BLOCK,
        )
    ids = torch.nonzero(valid).squeeze(1)  # one host sync
    if len(ids) == 0:
        return None
    params, boxes, rects = params[ids], boxes[ids], rects[ids].contiguous()
    count = rects[:, 3].long()
    starts = torch.cumsum(count, 0) - count
    total = int(starts[-1] + count[-1])  # the other host sync
    keys = torch.empty(total, dtype=torch.int64, device=device)
    splats = torch.empty(total, dtype=torch.int64, device=device)
    if total > 0:
        _emit_kernel[(triton.cdiv(len(ids), EMIT_SPLATS),)](
            rects,
            starts,
            params[:, 3].contiguous(),
            keys,
            splats,
            len(ids),
            tiles_x,
            SPLATS=EMIT_SPLATS,
            TILES=EMIT_TILES,
        )
    keys, perm = torch.sort(keys, stable=True)
    order = splats[perm]
    # each tile's first pair, from the sorted tiles (bincount would sync the host on CUDA)
    edges = torch.arange(tiles_x * tiles_y + 1, device=device)
    bounds = torch.searchsorted(keys >> 32, edges)
    offsets, counts = bounds[:-1], bounds[1:] - bounds[:-1]
    colors = torch.zeros(0, 3, device=device)
    if with_colors:
        colors = view_colors(g, ids, camera.center.to(device))
    proj = ProjectedSplats(
        kind=g.kind,
        ids=ids,
        means2d=params[:, :2],
        depths=params[:, 3],
        bbox=boxes,
        opacities=params[:, 2],
        colors=colors,
        conics=None if surfel else params[:, 4:7],
        transforms=params[:, 4:].reshape(-1, 3, 3) if surfel else None,
    )
    return TiledView(
        proj, params, order, offsets, counts, camera.width, camera.height, tiles_x, tiles_y
    )


def chosen_tile_view():
    """The `tile_view(gaussians, camera, near, with_colors)` this process's Triton walks take:
    PyTorch's (`triton_vote.tile_view`) or, with SAGONLINE_TRITON_PREPARE=fused,
    `tile_view_fused`."""
    return tile_view_fused if triton_prepare() == "fused" else tile_view
