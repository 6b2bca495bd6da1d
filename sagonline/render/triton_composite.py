"""The Triton walk's composite (`triton_vote._walk_kernel` with COMPOSITE): the label renders
and, on a CUDA machine without gsplat, the image renderer. Features of each splat (one-hot
labels, or the view's SH colours and any per-Gaussian features) are composited front to back by
the rules of `rasterize`, with the most visible Gaussian per pixel and, for images, the
weighted depth and the final T. No gradients: a render that needs them takes the PyTorch twin
(`render.api.render`)."""

from __future__ import annotations

import torch

from sagonline.render.rasterize import T_STOP, RenderOutput, image_output
from sagonline.render.triton_prepare import chosen_tile_view
from sagonline.render.triton_vote import walk
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians


def composite_triton(
    gaussians: Gaussians,
    camera: Camera,
    rows: torch.Tensor | None,  # [N, F] per-Gaussian features, or None (colours)
    *,
    t_stop: float = T_STOP,
    near: float = 0.01,
    image: bool = False,
):
    """The composite walk: (H, W, F) composited features (the view's SH colours, then `rows`,
    with `image`; `rows` alone otherwise), (H, W) the most visible Gaussian (-1: none), and with
    `image` (H, W) the weighted depth and the final T (None otherwise). No gradients."""
    device = gaussians.device
    H, W = camera.height, camera.width
    f = (3 if image else 0) + (rows.shape[1] if rows is not None else 0)
    kp = max(2, 1 << (f - 1).bit_length())  # a power of two, as tl.arange needs
    out = torch.zeros(H * W, kp, device=device)
    best = torch.full((H * W,), -1, dtype=torch.int64, device=device)
    depth = torch.zeros(H * W, device=device)
    trans = torch.ones(H * W, device=device)
    with torch.no_grad():
        view = chosen_tile_view()(gaussians, camera, near, with_colors=image)
        if view is not None:
            parts = ([view.proj.colors] if image else []) + (
                [rows[view.proj.ids]] if rows is not None else []
            )
            packed = torch.zeros(len(view.proj), kp, device=device)
            if parts:
                packed[:, :f] = torch.cat([part.float() for part in parts], dim=1)
            walk(
                view,
                out,
                f,
                rows=packed,
                best=best,
                depth=depth,
                trans=trans,
                t_stop=t_stop,
                image=image,
            )
    feats = out[:, :f].view(H, W, f)
    if not image:
        return feats, best.view(H, W), None, None
    return feats, best.view(H, W), depth.view(H, W), trans.view(H, W)


def label_weights_triton(
    gaussians: Gaussians,
    camera: Camera,
    splat_labels: torch.Tensor,  # [N] long, -1 none
    num_labels: int,
    *,
    t_stop: float = T_STOP,
) -> tuple[torch.Tensor, torch.Tensor]:  # [H, W, K] weights, [H, W] ids
    """The label renders' walk: (H, W, K) composited one-hot weights of the Gaussians whose
    label (splat_labels (N,), -1: none) is >= 0, and (H, W) the most visible Gaussian (-1:
    none)."""
    onehot = torch.zeros(len(splat_labels), num_labels, device=gaussians.device)
    known = splat_labels >= 0
    onehot[known.nonzero().squeeze(1), splat_labels[known]] = 1.0
    weights, best, _, _ = composite_triton(gaussians, camera, onehot, t_stop=t_stop)
    return weights, best


def rasterize_triton(
    gaussians: Gaussians,
    camera: Camera,
    *,
    background: torch.Tensor | None = None,  # [3]
    features: torch.Tensor | None = None,  # [N, F]
    t_stop: float = T_STOP,
    near: float = 0.01,
    return_ids: bool = False,
) -> RenderOutput:
    """Render one view on CUDA through the composite walk (no gradients); outputs as
    `rasterize`: rgb over the background, alpha, weighted depth, features, most visible ids."""
    feat, best, depth, trans = composite_triton(
        gaussians, camera, features, t_stop=t_stop, near=near, image=True
    )
    ids = best if return_ids else None
    return image_output(feat, trans, depth, background, features is not None, ids)
