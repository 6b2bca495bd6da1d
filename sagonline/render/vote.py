"""The vote as one op: one view's votes as an (N, K) label histogram, `vote_histogram`.

The rule (`render.rule.VoteRule`), the paper's Rasterization-aware Geometric Consensus at the
pixel level: each pixel walks its Gaussians front to back; Gaussian i votes for the pixel's
label when the transmittance before it is T_i > eps and it reaches the pixel (alpha_i > 0),
and, with `delta`, only if its projected centre lies within delta pixels of the pixel centre.
A vote is +1 (weighting "count", RGC) or alpha_i T_i ("blend", FlashSplat and the weighted
mean). A pixel's walk ends once T <= eps. Turning histograms into labels is
`sagonline.vote.consensus`'s business, not this module's.

One op, `vote_into` (and `vote_histogram`, which returns the histogram), and one function of
the same name and signature per implementation, `vote_into(gaussians, camera, labels, hist,
rule) -> pairs voted` (as gsplat pairs `_wrapper.py` with `_torch_impl.py`):
- torch (`_torch_impl.py`): the readable reference, `rasterize`'s tiled walk streaming its
  (pixel, Gaussian) pairs into a scatter-add (CPU or CUDA);
- native (`native.py`): the compiled CPU pass (csrc/prepare_view.cpp: projection and tile
  lists; csrc/vote_cpu.cpp: an 8-pixel-wide walk in C++, AVX2 chosen at run time);
- triton (`triton_vote.py`): the fused trace-and-vote kernel, one launch per view, on CUDA; the
  tests run the same kernel on the CPU through Triton's interpreter; `triton_vote_chunk.py`'s
  chunked vote counts on CUDA (`backends.triton_vote_kernel`; SAGONLINE_TRITON_VOTE chooses);
- gsplat (`_torch_impl.py`, `via="gsplat"`): gsplat's per-pixel ids walked in depth batches
  from Python (CUDA; the former path, kept to compare against).
"""

from __future__ import annotations

import functools

import torch

from sagonline.render.backends import (
    TRITON_VOTE_KERNELS,
    resolve_vote_backend,
    triton_vote_kernel,
)
from sagonline.render.rule import VoteRule
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians


def vote_histogram(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [H, W] long label ids in [0, num_labels), the view's mask
    num_labels: int,
    rule: VoteRule,
    *,
    backend: str = "auto",
    out: torch.Tensor | None = None,  # [N, K] float64 running histogram, added into
) -> torch.Tensor:  # [N, K] float64
    """Add one view's votes under `rule` to an (N, K) histogram and return it (a new zero one
    when `out` is None; on the Gaussians' device). backend: one of VOTE_BACKENDS (see
    `resolve_vote_backend`)."""
    if out is None:
        out = torch.zeros(len(gaussians), num_labels, dtype=torch.float64, device=gaussians.device)
    if out.shape[1] != num_labels:
        raise ValueError(f"out has {out.shape[1]} labels, not {num_labels}")
    vote_into(gaussians, camera, labels, rule, out, backend=backend)
    return out


def vote_into(
    gaussians: Gaussians,
    camera: Camera,
    labels: torch.Tensor,  # [H, W] long label ids in [0, K), the view's mask
    rule: VoteRule,
    hist: torch.Tensor,  # [N, K] float64 running histogram, added into
    *,
    backend: str = "auto",
) -> int:
    """The op itself: one view's votes under `rule` added into `hist`; returns how many
    (pixel, Gaussian) pairs voted (for the count rule, what it added)."""
    n, k = len(gaussians), hist.shape[1] if hist.dim() == 2 else 0
    if not isinstance(rule, VoteRule):
        raise TypeError(f"rule must be a VoteRule, got {type(rule).__name__}")
    labels = torch.as_tensor(labels).long()  # where they were given (a mask: the host's)
    if labels.shape != (camera.height, camera.width):
        raise ValueError(
            f"labels are {tuple(labels.shape)}; the view renders {camera.height}x{camera.width}"
        )
    if labels.numel():  # read where they are: on the host no wait on a GPU; on one, one copy
        low, high = torch.stack(torch.aminmax(labels)).tolist()
        if low < 0 or high >= k:
            raise ValueError(f"label ids must lie in [0, {k})")
    labels = on_device(labels, gaussians.device, k)
    if hist.shape != (n, k) or hist.dtype != torch.float64 or not hist.is_contiguous():
        raise ValueError(f"out must be a contiguous ({n}, {k}) float64 histogram")
    chosen = resolve_vote_backend(backend, gaussians.device)
    if n == 0:
        return 0
    with torch.profiler.record_function(f"vote_into ({chosen})"):  # named in a profile
        run = implementation(chosen, rule.weighting, k)
        return int(run(gaussians, camera, labels, hist, rule))


def label_type(num_labels: int) -> torch.dtype:
    """The narrowest integer type that holds label ids in [0, num_labels)."""
    return torch.uint8 if num_labels <= 256 else torch.int32


def on_device(
    labels: torch.Tensor,  # [H, W] long label ids in [0, num_labels), checked
    device: torch.device,
    num_labels: int,
) -> torch.Tensor:  # [H, W] long on `device`
    """The view's mask where the Gaussians are. To another device it crosses in `label_type`
    (a byte a pixel for up to 256 labels: 0.5 MB of a 960x540 view, not 4.1 MB of int64) and is
    widened there; where it already is, it is the same tensor."""
    if labels.device == torch.device(device):
        return labels
    return labels.to(label_type(num_labels)).to(device).long()


def implementation(backend: str, weighting: str = "count", num_labels: int = 0):
    """The `vote_into(gaussians, camera, labels, hist, rule)` of a backend, for a rule of
    `weighting` over `num_labels` labels (which Triton kernel votes:
    `backends.triton_vote_kernel`)."""
    if backend == "native":
        from sagonline.render.native import vote_into

        return vote_into
    if backend == "triton":  # the splat walk, or the chunked vote (`triton_vote_kernel`)
        from sagonline.render import triton_vote
        from sagonline.render.triton_prepare import chosen_tile_view

        chunk, warps = TRITON_VOTE_KERNELS[triton_vote_kernel(weighting, num_labels)]
        prepare = chosen_tile_view()  # PyTorch's tile lists or the fused kernels'
        if chunk:
            from sagonline.render.triton_vote_chunk import vote_chunks

            launch = functools.partial(vote_chunks, chunk=chunk, warps=warps)
            return functools.partial(triton_vote.vote_into, launch=launch, prepare=prepare)
        return functools.partial(triton_vote.vote_into, prepare=prepare)
    from sagonline.render import _torch_impl

    if backend == "gsplat":
        return functools.partial(_torch_impl.vote_into, via="gsplat")
    return _torch_impl.vote_into
