"""The vote as one op: one view's votes as an (N, K) label histogram, `vote_histogram`.

The rule, the paper's Rasterization-aware Geometric Consensus at the pixel level: each pixel
walks its Gaussians front to back; Gaussian i votes for the pixel's label when the
transmittance before it is T_i > t_min and it reaches the pixel (alpha_i > 0), and, with
`max_distance`, only if its projected centre lies within that many pixels of the pixel centre.
A vote is +1 (weighting "count", RGC) or alpha_i T_i ("blend", FlashSplat and the weighted
mean). A pixel's walk ends once T <= t_min. Turning histograms into labels is
`sagonline.consensus`'s business, not this module's.

One op, several implementations (as gsplat pairs `_wrapper.py` with `_torch_impl.py`):
- torch: the readable reference, `rasterize`'s tiled walk streaming its (pixel, Gaussian) pairs
  into a scatter-add (CPU or CUDA);
- native: the compiled CPU pass (csrc/vote_cpu.cpp: projection, tile lists and an 8-pixel-wide
  walk in C++, AVX2 chosen at run time);
- triton: the fused trace-and-vote kernel (`triton_vote.py`), one launch per view, on CUDA; the
  tests run the same kernel on the CPU through Triton's interpreter;
- gsplat: gsplat's per-pixel ids walked in depth batches from Python (CUDA; the former path, kept
  to compare against).
"""

from __future__ import annotations

import functools

import torch

from sagonline.cameras import Camera
from sagonline.gaussians import Gaussians
from sagonline.render.rasterize import TraceChunk, TraceRequest, rasterize

VOTE_BACKENDS = ("torch", "native", "triton", "gsplat")
WEIGHTINGS = ("count", "blend")


def resolve_vote_backend(backend: str, device: torch.device | str) -> str:
    """The vote implementation for a renderer backend: 'auto' takes the fastest one the device
    has (CPU: native; CUDA: triton, else gsplat), 'gsplat' on CUDA prefers the fused Triton
    kernel when Triton is installed; 'torch', 'native' and 'triton' are taken as asked."""
    from sagonline.render.api import resolve_backend

    if backend == "triton":
        return backend
    if backend not in ("auto", "gsplat"):
        return resolve_backend(backend, device)
    if torch.device(device).type == "cuda":
        from sagonline.render.triton_vote import triton_available

        if triton_available():
            return "triton"
    return resolve_backend(backend, device)


def vote_histogram(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,
    num_labels: int,
    *,
    t_min: float = 0.01,
    max_distance: float | None = 2.0,
    weighting: str = "count",
    backend: str = "auto",
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Add one view's votes to an (N, K) float64 histogram and return it.

    labels: (H, W) long label ids in [0, num_labels) of the view's mask; out: the running
    (N, K) float64 histogram on the Gaussians' device (a new zero one when None). backend: one
    of VOTE_BACKENDS or 'auto' (see `resolve_vote_backend`)."""
    n, k = len(gaussians), num_labels
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting {weighting!r} is not one of {WEIGHTINGS}")
    labels = torch.as_tensor(labels, device=gaussians.device).long()
    if labels.shape != (camera.height, camera.width):
        raise ValueError(
            f"labels are {tuple(labels.shape)}; the view renders {camera.height}x{camera.width}"
        )
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= k):
        raise ValueError(f"label ids must lie in [0, {k})")
    if out is None:
        out = torch.zeros(n, k, dtype=torch.float64, device=gaussians.device)
    if out.shape != (n, k) or out.dtype != torch.float64 or not out.is_contiguous():
        raise ValueError(f"out must be a contiguous ({n}, {k}) float64 histogram")
    chosen = resolve_vote_backend(backend, gaussians.device)
    if n == 0:
        return out
    implementation = _implementation(chosen)
    implementation(
        gaussians,
        camera,
        labels,
        out,
        t_min=float(t_min),
        max_distance=max_distance,
        weighting=weighting,
    )
    return out


def _implementation(backend: str):
    """The function behind a backend; each takes (gaussians, camera, labels (H, W), hist (N, K),
    *, t_min, max_distance, weighting) and adds into hist."""
    if backend == "native":
        from sagonline.render.native import vote_native

        return vote_native
    if backend == "triton":
        from sagonline.render.triton_vote import vote_triton

        return vote_triton
    if backend == "gsplat":
        return functools.partial(vote_by_trace, backend="gsplat")
    return vote_by_trace


def vote_by_trace(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,
    hist: torch.Tensor,
    *,
    t_min: float,
    max_distance: float | None,
    weighting: str,
    backend: str = "torch",
) -> None:
    """The reference: a renderer's streamed trace (`rasterize`, or gsplat's ids) reduced into
    hist (N, K) by `add_pairs`."""
    flat = labels.flatten()

    def add(chunk: TraceChunk) -> None:
        add_pairs(hist, flat, chunk, weighting=weighting)

    request = TraceRequest(add, t_min=t_min, max_distance=max_distance)
    if backend == "gsplat":
        from sagonline.render.gsplat_backend import rasterize_gsplat

        rasterize_gsplat(gaussians, camera, trace=request)
    else:
        rasterize(gaussians, camera, trace=request)


def add_pairs(
    hist: torch.Tensor, labels: torch.Tensor, chunk: TraceChunk, *, weighting: str
) -> int:
    """Add the votes of traced (pixel, Gaussian) pairs, already filtered by the rule
    (`TraceRequest.keeps`), to hist (N, K); labels: (H*W,) the view's mask. Returns the votes
    cast."""
    k = hist.shape[1]
    index = chunk.gaussian * k + labels[chunk.pixel]
    if weighting == "count":
        weight = torch.ones_like(index, dtype=hist.dtype)
    else:
        weight = (chunk.alpha * chunk.transmittance).to(hist.dtype)
    hist.view(-1).scatter_add_(0, index, weight)
    return int(index.numel())
