"""One entry point for every backend: `render(scene, camera, backend=...)`."""

from __future__ import annotations

import inspect

import numpy as np
import torch

from sagonline.render.backends import resolve_backend, resolve_vote_backend
from sagonline.render.rasterize import RenderOutput, rasterize
from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

# Every option `render` takes: those of the readable twin, `rasterize`.
RENDER_OPTIONS = frozenset(inspect.signature(rasterize).parameters) - {"gaussians", "camera"}


def render(
    gaussians: Gaussians, camera: Camera, *, backend: str = "torch", **options
) -> RenderOutput | None:
    """Render (and optionally trace) one view; options as in `rasterize`. The native CPU kernel
    renders images, features and most-visible ids; a trace (`TraceRequest`) runs on the tiled
    PyTorch path there (the vote has its own compiled pass: `vote_histogram`). `background` may
    be a tensor [3] or three floats. An option the chosen backend cannot honour raises, as does
    a misspelt one."""
    unknown = sorted(set(options) - RENDER_OPTIONS)
    if unknown:  # a misspelt option would otherwise do nothing
        raise TypeError(
            f"render(): unknown option(s) {unknown}; the options are {sorted(RENDER_OPTIONS)}"
        )
    if options.get("background") is not None and not torch.is_tensor(options["background"]):
        options["background"] = torch.tensor(options["background"], dtype=torch.float32)  # r,g,b
    chosen = resolve_backend(backend, gaussians.device)
    if chosen in ("native", "triton") and options.get("trace") is not None:
        chosen = "torch"
    if chosen == "triton" and _needs_grad(gaussians, options.get("features")):
        chosen = "torch"  # the Triton walk has no backward pass
    fn = _backend_function(chosen)
    if _cannot(fn, options):
        # what the caller needs (ids, say) decides, not the renderer picked for images: gsplat
        # draws no ids, so a diagnosis on a GPU with gsplat renders its ids with another backend
        fn = _backend_function(capable_backend(chosen, options, gaussians.device))
    return fn(gaussians, camera, **{k: v for k, v in options.items() if k in _accepted(fn)})


def _accepted(fn) -> set[str]:
    return set(inspect.signature(fn).parameters)


def _cannot(fn, options: dict) -> list[str]:
    """The options given (not None or False) that the backend function does not take."""
    return sorted(
        k for k, v in options.items() if k not in _accepted(fn) and v not in (None, False)
    )


def capable_backend(chosen: str, options: dict, device) -> str:
    """`chosen`, or where it cannot honour `options` the fastest backend on the device that can
    (CUDA: triton, then torch; CPU: native, then torch); ValueError when none can."""
    from sagonline.render.backends import _device_type, installed

    have = installed()
    order = ("triton", "torch") if _device_type(device) == "cuda" else ("native", "torch")
    for name in (chosen, *order):
        if name in ("triton", "native") and not have.has(name):
            continue
        if not _cannot(_backend_function(name), options):
            return name
    raise ValueError(f"no renderer here honours {_cannot(_backend_function(chosen), options)}")


def _needs_grad(gaussians: Gaussians, features: torch.Tensor | None) -> bool:
    """Whether a render would be differentiated: grad mode on and a parameter requiring it."""
    if not torch.is_grad_enabled():
        return False
    tensors = [
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        gaussians.sh,
        features,
    ]
    return any(t is not None and t.requires_grad for t in tensors)


def _backend_function(name: str):
    if name == "gsplat":
        from sagonline.render.gsplat_backend import rasterize_gsplat

        return rasterize_gsplat
    if name == "native":
        from sagonline.render.native import rasterize_native

        return rasterize_native
    if name == "triton":
        from sagonline.render.triton_composite import rasterize_triton

        return rasterize_triton
    return rasterize


def render_coverage(
    gaussians: Gaussians,
    camera: Camera,
    groups: torch.Tensor,  # [G, N] bool, the Gaussians of each group
    *,
    backend: str = "torch",
) -> tuple[torch.Tensor, torch.Tensor]:  # [G, H, W] alpha, [G, H, W] alpha-weighted depth
    """Each group of Gaussians drawn alone: its alpha and alpha-weighted depth (divide by alpha
    for the surface's depth), as `render` gives them for that group's Gaussians. On the CPU's
    compiled kernel, 8 groups a walk without colours (`coverage_native`: no SH, no autograd);
    elsewhere one `render` per group."""
    if resolve_backend(backend, gaussians.device) == "native":
        from sagonline.render.native import coverage_native

        drawn = [
            coverage_native(gaussians, camera, groups[i : i + 8]) for i in range(0, len(groups), 8)
        ]
        return torch.cat([a for a, _ in drawn]), torch.cat([d for _, d in drawn])
    alphas, depths = [], []
    for members in groups.to(gaussians.device):
        if not bool(members.any()):  # nothing to draw: no coverage, no depth
            empty = torch.zeros(camera.height, camera.width, device=gaussians.device)
            alphas.append(empty)
            depths.append(empty)
            continue
        out = render(gaussians.subset(members), camera, backend=backend)
        alphas.append(out.alpha)
        depths.append(out.depth)
    return torch.stack(alphas), torch.stack(depths)


def to_uint8(
    rgb: torch.Tensor,  # [H, W, 3] linear in [0, 1]
) -> np.ndarray:
    """(H, W, 3) linear RGB in [0, 1] -> uint8 image (clipped, rounded)."""
    return (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def render_labels(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [N] long in [-1, num_labels): -1 unlabelled, 0 background, 1.. objects
    num_labels: int,
    *,
    min_weight: float = LABEL_MIN_WEIGHT,
    mode: str = "onehot",
    backend: str = "torch",
) -> torch.Tensor:  # [H, W] long in [0, num_labels)
    """A label mask of one view from per-Gaussian labels (-1: unlabelled, the one encoding).

    mode "onehot": the labels of the labelled Gaussians (background included) are composited as
    one-hot attributes; a pixel takes the label of largest weight, or 0 where the labelled
    weight is below `min_weight`. Unlabelled Gaussians still occlude. mode "ids": each pixel
    takes the label of its single most visible Gaussian (largest blend weight; 0 where that one
    is unlabelled). The compiled CPU kernel and, on CUDA, the Triton walk render both without
    shading; the torch backend (and gsplat without Triton) composite one-hot features with the
    PyTorch rasterizer.
    """
    return _labels_and_surface(gaussians, camera, labels, num_labels, min_weight, mode, backend)[0]


def render_labels_and_surface(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [N] long in [-1, num_labels)
    num_labels: int,
    *,
    min_weight: float = LABEL_MIN_WEIGHT,
    backend: str = "torch",
) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None]:  # 4x [H, W]
    """`render_labels`' (H, W) mask (mode "onehot") and, where its walk is the compiled
    kernel's, the view's surface from that same walk: (H, W) alpha, alpha-weighted depth and
    most visible Gaussians, `native.surface_native`'s bits; None on any other backend."""
    return _labels_and_surface(gaussians, camera, labels, num_labels, min_weight, "onehot", backend)


def _labels_and_surface(gaussians, camera, labels, num_labels, min_weight, mode, backend):
    """`render_labels_and_surface` in either mode, the labels checked first."""
    labels = labels.to(gaussians.device).long()
    if labels.shape != (len(gaussians),):
        raise ValueError(f"labels has shape {tuple(labels.shape)}, expected ({len(gaussians)},)")
    if labels.numel() and (labels.min() < -1 or labels.max() >= num_labels):
        raise ValueError(
            f"label ids must lie in [-1, {num_labels}) (-1: unlabelled); got "
            f"[{int(labels.min())}, {int(labels.max())}]"
        )
    if mode not in ("onehot", "ids"):
        raise ValueError(f"label render mode {mode!r} is not 'onehot' or 'ids'")
    weights, ids, surface = _label_walk(gaussians, camera, labels, num_labels, mode, backend)
    if mode == "ids":
        chosen = labels[ids.clamp_min(0)].clamp_min(0)
        return torch.where(ids >= 0, chosen, torch.zeros_like(ids)), surface
    best = weights.argmax(dim=-1)
    return torch.where(weights.sum(-1) >= min_weight, best, torch.zeros_like(best)), surface


def _label_walk(gaussians, camera, splat_labels, num_labels, mode, backend):
    """(H, W, K) one-hot weights (None for mode 'ids'), (H, W) most visible Gaussians and, on
    the compiled kernel, the surface (alpha, depth, ids; None elsewhere)."""
    chosen = resolve_vote_backend(backend, gaussians.device)
    if chosen == "native":
        from sagonline.render.native import label_walk_native

        weights, ids, alpha, depth = label_walk_native(
            gaussians, camera, splat_labels, num_labels, with_weights=mode == "onehot"
        )
        return weights, ids, (alpha, depth, ids)
    if chosen == "triton":
        from sagonline.render.triton_composite import label_weights_triton

        return *label_weights_triton(gaussians, camera, splat_labels, num_labels), None
    if mode == "ids":  # gsplat keeps no per-pixel argmax: the tiled PyTorch path
        return None, rasterize(gaussians, camera, return_ids=True).ids, None
    onehot = torch.nn.functional.one_hot(splat_labels.clamp_min(0), num_labels).float()
    onehot *= (splat_labels >= 0)[:, None].float()
    return render(gaussians, camera, features=onehot, backend=backend).features, None, None
