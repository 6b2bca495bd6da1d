"""Where a fit starts: the training/held-out split and the draw of the training views, random
points in the training frusta, and the start points completed with random ones behind what
sparse points already explain."""

from __future__ import annotations

import math

import numpy as np
import torch

from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import SH_C0


def split_views(
    cameras: list[Camera], every: int, train_every: int = 1
) -> tuple[list[int], list[int]]:
    """Indices of training and held-out views: every `every`-th (sorted by name) is held out;
    of the rest, every `train_every`-th trains (the others are left out of both)."""
    order = sorted(range(len(cameras)), key=lambda i: cameras[i].name)
    held = [i for k, i in enumerate(order) if every and k % every == 0]
    train = [i for i in order if i not in held][::train_every]
    if train_every > 1 and len(train) < 2:
        raise ValueError(
            f"fit.train_every={train_every}: leaves {len(train)} training photograph(s) of "
            f"{len(cameras)}; a fit needs at least 2"
        )
    return train, held


def view_draws(seed: int, step: int, num_views: int) -> np.random.Generator:
    """The draw of each step's training view (one of `num_views`) at `step`: seeded by the
    fit's seed and advanced past the steps already trained, one draw each, so a fit resumed
    from a checkpoint draws the views that one run straight through draws."""
    rng = np.random.default_rng(seed)
    for _ in range(step):
        rng.integers(num_views)
    return rng


def init_from_views(
    cameras: list[Camera],
    images: list[torch.Tensor],  # V of [H, W, 3] in [0, 1]
    count: int,
    near_far: tuple[float, float],
    rng: np.random.Generator,
    min_visible: float = 0.5,
    near_per_view: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Random points in the training frusta: a random pixel of a random view at a random
    (log-uniform) depth between near and far, coloured by that pixel, kept when at least
    `min_visible` of the views see it (for orbits: the region they all look at; a fallback
    keeps the most visible candidates; 0 keeps every point). `near_per_view` (V,) replaces
    `near` per view. (P, 3) xyz, (P, 3) rgb in [0, 1]."""
    near, far = near_far
    m = 8 * count if min_visible > 0 else count
    views = rng.integers(len(cameras), size=m)
    u, v = rng.uniform(0, 1, m), rng.uniform(0, 1, m)
    lo = np.full(m, math.log(near)) if near_per_view is None else np.log(near_per_view[views])
    depth = np.exp(rng.uniform(lo, math.log(far)))
    xyz, rgb = np.empty((m, 3)), np.empty((m, 3))
    for i in range(len(cameras)):
        sel = views == i
        cam, img = cameras[i], images[i]
        px, py = u[sel] * cam.width, v[sel] * cam.height
        rays = np.stack([px, py, np.ones_like(px)], 1) @ np.linalg.inv(cam.K.double().numpy()).T
        p_cam = rays * depth[sel, None]
        R, t = cam.rotation.double().numpy(), cam.translation.double().numpy()
        xyz[sel] = (p_cam - t) @ R
        rgb[sel] = (
            img[py.astype(int).clip(0, cam.height - 1), px.astype(int).clip(0, cam.width - 1)]
            .cpu()
            .numpy()
        )
    if min_visible <= 0:
        return xyz, rgb
    pts = torch.tensor(xyz, dtype=torch.float32)
    seen = np.zeros(m)
    for cam in cameras:
        seen += cam.in_frame(pts)[0].numpy()
    order = np.argsort(-seen, kind="stable")
    keep = order[seen[order] >= min_visible * len(cameras)][:count]
    if len(keep) < count // 2:
        keep = order[:count]
    return xyz[keep], rgb[keep]


def median_depth(cam: Camera, xyz: np.ndarray, default: float) -> float:
    """Median camera depth of the points `cam` sees (`default` when it sees none)."""
    seen, z = cam.in_frame(torch.tensor(xyz, dtype=torch.float32))
    return float(z[seen].median()) if bool(seen.any()) else default


def start_points(
    cameras: list[Camera],
    images: list[torch.Tensor],  # V of [H, W, 3] in [0, 1]
    points: tuple[np.ndarray, np.ndarray] | None,
    near_far: tuple[float, float],
    init_points: int,
    background_points: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """The fit's start points, (P, 3) xyz and (P, 3) rgb: `points` when given, completed with
    `background_points` random points in the frusta behind them (sparse points sit on textured
    surfaces; what they miss, walls, floor, sky, gets random points behind what the points
    explain, since random points in front of the surfaces would start as floaters); without
    points, `init_points` random points in the frusta."""
    if points is None or len(points[0]) == 0:
        return init_from_views(cameras, images, init_points, near_far, rng)
    if not background_points:
        return points
    behind = np.array([median_depth(c, points[0], near_far[0]) for c in cameras])
    extra = init_from_views(
        cameras,
        images,
        background_points,
        near_far,
        rng,
        min_visible=0.0,
        near_per_view=np.minimum(behind, near_far[1] * 0.99),
    )
    return tuple(np.concatenate([a, b]) for a, b in zip(points, extra, strict=True))


def initial_params(
    xyz: np.ndarray,  # [N, 3] start points
    rgb: np.ndarray,  # [N, 3] their colours in [0, 1]
    kind: str,
    sh_degree: int,
    rng: np.random.Generator,
    device: str = "cpu",
) -> dict[str, torch.Tensor]:  # means [N, 3], log_scales [N, 2 or 3], quats [N, 4], ...
    """The raw parameters of a fit's first Gaussians, one per start point: scale the distance to
    the 3 nearest neighbours (as 3DGS; 2 axes for 2DGS surfels), random rotation, opacity 0.1,
    SH degree 0 from the colour: means (N, 3), log_scales (N, 2) for 2DGS or (N, 3), quats
    (N, 4), opacity_logit (N,), sh_dc (N, 1, 3), sh_rest (N, (sh_degree + 1)^2 - 1, 3)."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    d, _ = cKDTree(xyz).query(xyz, k=min(4, n))
    d = np.sqrt(np.mean(np.asarray(d).reshape(n, -1)[:, 1:] ** 2, axis=1)).clip(1e-7)
    dims = 2 if kind == "2dgs" else 3
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3, device=device)
    sh[:, 0] = (torch.tensor(rgb, dtype=torch.float32, device=device) - 0.5) / SH_C0
    quats = torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32, device=device)
    log_scales = torch.log(torch.tensor(d, dtype=torch.float32, device=device))
    return {
        "means": torch.tensor(xyz, dtype=torch.float32, device=device),
        "log_scales": log_scales[:, None].repeat(1, dims),
        "quats": quats / quats.norm(dim=1, keepdim=True),
        "opacity_logit": torch.full((n,), math.log(0.1 / 0.9), device=device),
        "sh_dc": sh[:, :1].contiguous(),
        "sh_rest": sh[:, 1:].contiguous(),
    }
