"""The fit's losses and image metrics: L1 + D-SSIM, PSNR, the needle penalty on surfels,
2DGS's geometric regularisers (depth distortion, normal consistency) and the rendered depth's
consistency with neighbouring photographs.

The regularisers are computed from composited per-splat attributes (`splat_geometry`: the
splat's normal and normalised depth), so their gradients run through whichever rasterizer renders
the view, the compiled kernel's hand-written backward included: no kernel of their own."""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians, quat_to_normal, quat_to_rotmat


@functools.lru_cache(maxsize=16)
def ssim_window(
    window: int, sigma: float, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:  # [3, 1, window, window]
    """SSIM's Gaussian window, one per channel for a grouped convolution; made once per size,
    type and device (a fit step would otherwise make it anew, a dozen launches on a GPU)."""
    g = torch.exp(-((torch.arange(window, device=device) - window // 2) ** 2) / (2 * sigma**2))
    g = (g / g.sum()).to(dtype)
    return (g[:, None] * g[None, :]).expand(3, 1, window, window)


def ssim(
    a: torch.Tensor,  # [H, W, 3] in [0, 1]
    b: torch.Tensor,  # [H, W, 3] in [0, 1]
    window: int = 11,
    sigma: float = 1.5,
    weights: torch.Tensor | None = None,  # [H, W] per-pixel weights of the mean
) -> torch.Tensor:  # [] mean SSIM
    """Mean SSIM of two (H, W, 3) images in [0, 1] (Gaussian window, the usual constants),
    weighted per pixel by `weights` where given."""
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    k = ssim_window(window, sigma, a.dtype, a.device)
    pad = window // 2

    def blur(t):
        return F.conv2d(t, k, padding=pad, groups=3)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    if weights is None:
        return s.mean()
    per_pixel = s[0].mean(0)
    return (per_pixel * weights).sum() / weights.sum().clamp_min(1e-12)


class ReadLater:
    """Scalars computed on the device step by step, read on the host together when asked (one
    read a step would make the host wait for the GPU at every step)."""

    def __init__(self, values=()):
        self.read: list[float] = list(values)
        self.waiting: list[torch.Tensor] = []

    def append(self, value: torch.Tensor) -> None:  # [] on any device
        self.waiting.append(value.detach())

    def values(self) -> list[float]:
        if self.waiting:
            self.read.extend(torch.stack(self.waiting).tolist())
            self.waiting.clear()
        return self.read


def psnr_from_mse(mse: float) -> float:
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def mse(
    a: torch.Tensor,  # [H, W, 3]
    b: torch.Tensor,  # [H, W, 3]
) -> torch.Tensor:  # [] on their device
    return ((a - b) ** 2).mean()


def psnr(
    a: torch.Tensor,  # [H, W, 3]
    b: torch.Tensor,  # [H, W, 3]
) -> float:
    return psnr_from_mse(float(mse(a, b)))


def photometric_loss(
    rgb: torch.Tensor,  # [H, W, 3] render
    gt: torch.Tensor,  # [H, W, 3] photograph
    lambda_dssim: float,
    trim: float = 0.0,
) -> torch.Tensor:  # []
    """(1 - lambda) L1 + lambda (1 - SSIM) of two (H, W, 3) images. trim: the fraction of the
    pixels of largest L1 residual left out of both terms (a trimmed, robust loss: what no other
    photograph agrees with, a background that moved between photo sets, stops pulling the
    fit); 0: every pixel."""
    residual = (rgb - gt).abs().mean(-1)  # [H, W]
    if not trim:
        l1 = residual.mean()
        return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(rgb, gt))
    keep = trimmed_pixels(residual.detach(), trim)
    l1 = (residual * keep).sum() / keep.sum().clamp_min(1)
    agreed = torch.where(keep[..., None] > 0, rgb, gt)  # the trimmed pixels take no gradient
    return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(agreed, gt, weights=keep))


def trimmed_pixels(
    residual: torch.Tensor,  # [H, W] per-pixel residual
    trim: float,
) -> torch.Tensor:  # [H, W] float 1 kept, 0 left out
    """1 where a pixel's residual is not among the `trim` fraction of largest ones."""
    flat = residual.flatten()
    k = int(round(trim * flat.numel()))
    if k <= 0:
        return torch.ones_like(residual)
    cut = flat.kthvalue(flat.numel() - k).values
    return (residual <= cut).to(residual.dtype)


def anisotropy_penalty(
    log_scales: torch.Tensor,  # [N, 2] or [N, 3]
    max_aspect: float,
) -> torch.Tensor:  # []
    """Mean excess of each Gaussian's axis ratio over `max_aspect` (0 when none exceeds it):
    keeps surfels from turning into needles that look right only edge-on. log_scales: (N, 2|3)."""
    log_ratio = log_scales.max(dim=1).values - log_scales.min(dim=1).values
    return F.relu(torch.exp(log_ratio) - max_aspect).mean()


def opacity_entropy(
    opacity_logit: torch.Tensor,  # [N] or [N, 1]
) -> torch.Tensor:  # []
    """Mean binary entropy (nats) of the opacities: 0 where every Gaussian is opaque or gone,
    ln 2 at one half; its gradient pushes each opacity to the nearer of 0 and 1."""
    o = torch.sigmoid(opacity_logit)
    return (o * F.softplus(-opacity_logit) + (1 - o) * F.softplus(opacity_logit)).mean()


GEOMETRY_CHANNELS = 5  # splat_geometry's columns: normal (3), depth m, m^2


def splat_geometry(
    gaussians: Gaussians,
    camera: Camera,
    near: float,
    far: float,
) -> torch.Tensor:  # [N, 5] normal, depth m, m^2
    """(N, 5) per-splat attributes to composite for the regularisers: the unit normal in camera
    space, turned to face the camera (a surfel's third axis; a 3D Gaussian's shortest axis), and
    the centre depth z mapped as 2DGS maps it, m = far / (far - near) * (1 - near / z) (0 at the
    near plane, 1 at the far one), with m^2."""
    if gaussians.kind == "2dgs":
        normal = quat_to_normal(gaussians.quats)
    else:
        rot = quat_to_rotmat(gaussians.quats)
        axis = gaussians.scales.argmin(dim=1)
        normal = rot.gather(2, axis[:, None, None].expand(-1, 3, 1))[:, :, 0]
    R, t = camera.rotation.to(normal), camera.translation.to(normal)
    normal_cam = normal @ R.T
    centre_cam = gaussians.means @ R.T + t
    facing = torch.where((normal_cam * centre_cam).sum(1, keepdim=True) > 0, -1.0, 1.0)
    z = centre_cam[:, 2].clamp_min(near * 1e-3)
    m = far / (far - near) * (1 - near / z)
    return torch.cat([normal_cam * facing, m[:, None], (m * m)[:, None]], dim=1)


def depth_distortion(
    alpha: torch.Tensor,  # [H, W]
    m1: torch.Tensor,  # [H, W] composited m
    m2: torch.Tensor,  # [H, W] composited m^2
) -> torch.Tensor:  # []
    """2DGS's depth distortion, sum over pairs i < j of w_i w_j (m_i - m_j)^2 per pixel, as
    alpha * M2 - M1^2 with M1 = sum w_i m_i, M2 = sum w_i m_i^2 and alpha = sum w_i (the same
    sum, expanded); mean over pixels. alpha, m1, m2: (H, W) composites of `splat_geometry`'s
    depth columns. Small when each ray's weight sits at one depth: it gathers fog into surfaces."""
    return (alpha * m2 - m1 * m1).clamp_min(0).mean()


def surface_points(
    depth: torch.Tensor,  # [H, W] alpha-weighted depth
    alpha: torch.Tensor,  # [H, W]
    camera: Camera,
) -> torch.Tensor:  # [H, W, 3] camera coordinates
    """(H, W, 3) each pixel centre's point at the expected depth (depth / alpha), in camera
    coordinates."""
    H, W = depth.shape
    z = depth / alpha.clamp_min(1e-6)
    K = camera.K.to(depth)
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=depth.dtype, device=depth.device) + 0.5,
        torch.arange(W, dtype=depth.dtype, device=depth.device) + 0.5,
        indexing="ij",
    )
    rays = torch.stack(
        [(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], torch.ones_like(xs)], -1
    )
    return rays * z[..., None]


def depth_normals(
    depth: torch.Tensor,  # [H, W] alpha-weighted depth
    alpha: torch.Tensor,  # [H, W]
    camera: Camera,
) -> torch.Tensor:  # [H, W, 3] unit normals
    """(H, W, 3) unit normals, facing the camera, of the surface given by the expected depth
    (depth / alpha) by central differences of the back-projected points; 0 on the border."""
    points = surface_points(depth, alpha, camera)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    inner = F.normalize(torch.linalg.cross(dy, dx), dim=-1)  # x right, y down: faces the camera
    return F.pad(inner.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)


def normal_consistency(
    rendered_normal: torch.Tensor,  # [H, W, 3] composited normals
    depth: torch.Tensor,  # [H, W]
    alpha: torch.Tensor,  # [H, W]
    camera: Camera,
) -> torch.Tensor:  # []
    """2DGS's normal consistency: mean over pixels of 1 - <N, alpha N_d>, N the composited splat
    normals (H, W, 3), N_d `depth_normals` of the rendered depth: the splats lie along the surface
    their depths describe. Both sides take the gradient, as in 2DGS; alpha weights without it."""
    surface = depth_normals(depth, alpha, camera) * alpha.detach()[..., None]
    return (1 - (rendered_normal * surface).sum(-1)).mean()


def nearest_views(
    cameras: list[Camera],
    k: int = 2,
) -> list[list[int]]:  # per camera: the indices of its k nearest others
    """For each camera, the `k` other cameras nearest by centre (fewer when there are fewer)."""
    centers = torch.stack([c.center for c in cameras]).double()
    dist = torch.cdist(centers, centers)
    dist.fill_diagonal_(math.inf)
    k = min(k, len(cameras) - 1)
    return [[int(j) for j in row.topk(k, largest=False).indices] for row in dist]


def neighbour_consistency(
    depth: torch.Tensor,  # [H, W] alpha-weighted depth
    alpha: torch.Tensor,  # [H, W]
    image: torch.Tensor,  # [H, W, 3] this view's photograph
    camera: Camera,
    neighbours: list[tuple[Camera, torch.Tensor]],  # (camera, [h, w, 3] photograph)
    min_alpha: float = 0.5,
) -> torch.Tensor:  # []
    """Photometric consistency of the rendered depth with neighbouring photographs: each pixel
    of this view (where alpha > `min_alpha`) is moved to its rendered surface point, projected
    into each neighbour and compared there (L1 of the colours); the smallest error over the
    neighbours counts (a pixel the surface hides in one neighbour shows in the other), mean over
    the pixels that land in some neighbour's frame. A surface drawn nearer or farther than the
    photographs agree on fetches the wrong colour: its gradient moves the depth, so floaters in
    front of the object are pulled onto the surfaces behind them. 0 without such pixels."""
    H, W = depth.shape
    in_camera = surface_points(depth, alpha, camera).reshape(-1, 3)
    R, t = camera.rotation.to(depth), camera.translation.to(depth)
    world = (in_camera - t) @ R  # R^T (x - t), row-wise
    errors = []
    for other, photo in neighbours:
        uv, zo = other.project(world)
        grid = torch.stack([2 * uv[:, 0] / other.width - 1, 2 * uv[:, 1] / other.height - 1], -1)
        fetched = F.grid_sample(
            photo.permute(2, 0, 1)[None].to(depth),
            grid.view(1, H, W, 2),
            align_corners=False,
            padding_mode="border",
        )[0].permute(1, 2, 0)
        inside = (zo.view(H, W) > 0) & (grid.view(H, W, 2).abs() < 1).all(-1)
        err = (fetched - image).abs().mean(-1)
        errors.append(torch.where(inside, err, torch.full_like(err, math.inf)))
    if not errors:
        return depth.sum() * 0
    best = torch.stack(errors).min(0).values
    used = (alpha.detach() > min_alpha) & torch.isfinite(best)
    return best[used].mean() if bool(used.any()) else depth.sum() * 0
