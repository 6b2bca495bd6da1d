"""A click in the 3D view -> a pixel of one view: the Gaussian the ray hits first, then the
view that sees it (`SegmentSession.click_from_ray`)."""

from __future__ import annotations

import numpy as np
import torch

from sagonline.core.errors import PromptError
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians


def pick_gaussian(
    gaussians: Gaussians,
    origin,  # [3] the ray's origin, world coordinates
    direction,  # [3] its direction (any length)
) -> np.ndarray:  # [3] float64
    """The centre of the front-most Gaussian (opacity >= 0.5) whose 3-sigma footprint the
    ray crosses; PromptError when it crosses none."""
    device = gaussians.device
    o = torch.as_tensor(origin, dtype=torch.float32, device=device)
    d = torch.as_tensor(direction, dtype=torch.float32, device=device)
    d = d / d.norm()
    rel = gaussians.means.detach().float() - o
    along = rel @ d
    off = (rel - along[:, None] * d).norm(dim=1)
    reach = 3.0 * gaussians.scales.detach().float().max(dim=1).values
    hit = (along > 0) & (off <= reach) & (gaussians.opacities.detach().float() >= 0.5)
    if not bool(hit.any()):
        raise PromptError("the click hits no Gaussian of the scene: click on the object")
    first = torch.where(hit, along, torch.full_like(along, float("inf"))).argmin()
    return gaussians.means[first].detach().float().cpu().numpy().astype(np.float64)


def view_for_point(
    cameras: list[Camera],
    depths: list[np.ndarray],  # [H, W] each view's surface depth (inf where nothing is drawn)
    point: np.ndarray,  # [3] world coordinates
    direction,  # [3] the click's ray
    views,
) -> tuple[int, float, float]:
    """(view, x, y): among `views`, the one that sees `point` (inside its image, not behind
    another surface) most nearly along the ray, and the point's pixel there."""
    ray = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    best = None
    for i in views:
        cam = cameras[i]
        centre = torch.as_tensor(point, dtype=torch.float32, device=cam.K.device)[None]
        inside, depth = cam.in_frame(centre)
        if not bool(inside[0]):
            continue
        xy = cam.project(centre)[0][0].cpu().numpy()
        x, y = float(xy[0]), float(xy[1])
        if float(depth[0]) > 1.05 * float(depths[i][int(y), int(x)]) + 1e-6:
            continue  # another surface is in front of it
        look = point - cam.center.cpu().numpy()
        angle = float(np.arccos(np.clip(look @ ray / np.linalg.norm(look), -1, 1)))
        if best is None or angle < best[0]:
            best = (angle, i, x, y)
    if best is None:
        views = list(views)
        where = (
            f"hidden or outside view {views[0]} ('{cameras[views[0]].name}'), the session's view"
            if len(views) == 1
            else "outside every view (or hidden in each)"
        )
        raise PromptError(f"the point clicked is {where}: click on what the views show")
    return best[1], best[2], best[3]
