"""What the viewer draws with: the scene's splat arrays for viser and the labels' colours over
them (a contrasting highlight per object; the surroundings as they are, dimmed or hidden)."""

from __future__ import annotations

import numpy as np
import torch

from sagonline.labels.colours import PALETTE, label_colors
from sagonline.scene.gaussians import SH_C0, Gaussians, quat_to_rotmat

SHOW = ("everything", "dimmed surroundings", "object alone")  # the panel's "show" choices
DIM = 0.25  # the surroundings' brightness when dimmed


def splat_arrays(g: Gaussians) -> dict[str, np.ndarray]:
    """viser's splat arrays: centers (N, 3), covariances (N, 3, 3), rgbs (N, 3) in [0, 1]
    (the SH's constant term), opacities (N, 1). Surfels get a thin third axis."""
    g = g.to("cpu")
    scales = g.scales.detach().float()
    if scales.shape[1] == 2:
        scales = torch.cat([scales, scales.min(dim=1, keepdim=True).values * 1e-2], 1)
    rot = quat_to_rotmat(g.quats.detach().float())
    cov = rot @ torch.diag_embed(scales**2) @ rot.transpose(1, 2)
    rgb = (0.5 + SH_C0 * g.sh[:, 0].detach().float()).clamp(0, 1)
    return {
        "centers": g.means.detach().float().numpy(),
        "covariances": cov.numpy(),
        "rgbs": rgb.numpy(),
        "opacities": g.opacities.detach().float().numpy()[:, None],
    }


def highlight_colours(rgbs: np.ndarray, labels: np.ndarray, num_labels: int) -> np.ndarray:
    """(num_labels, 3) in [0, 1]: for each object the palette colour farthest from its splats'
    own mean colour, each colour used once while the palette lasts (a crimson label on pink
    icing was barely visible; the highlight must contrast with what it covers)."""
    palette = label_colors(max(num_labels, 2)).astype(np.float32) / 255.0
    choices = PALETTE[1:].astype(np.float32) / 255.0  # black (background) is no highlight
    out, used = palette.copy(), set()
    for k in range(1, num_labels):
        members = labels == k
        if not members.any():
            continue
        mean = rgbs[members].mean(axis=0)
        order = np.argsort(-np.linalg.norm(choices - mean, axis=1))
        pick = next((int(i) for i in order if int(i) not in used), int(order[0]))
        used.add(pick)
        out[k] = choices[pick]
    return out


def label_tint(
    rgbs: np.ndarray, labels: np.ndarray, num_labels: int, show: str = SHOW[0]
) -> tuple[np.ndarray, np.ndarray]:
    """(rgbs (N, 3), visible (N,) bool): objects (labels >= 1) in a solid contrasting colour
    (`highlight_colours`), the rest in its own colour, dimmed, or hidden, as `show` says."""
    objects = labels >= 1
    colours = highlight_colours(rgbs, labels, max(num_labels, 2))
    rest = rgbs * DIM if show == "dimmed surroundings" and objects.any() else rgbs
    out = np.where(objects[:, None], colours[labels.clip(0)], rest).astype(np.float32)
    visible = objects if show == "object alone" and objects.any() else np.ones_like(objects)
    return out, visible
