"""Where the PyTorch runtime's tensors live (`segment.onnx_torch`): integer tensors (shapes,
indices) stay on the CPU, and an operator meeting one beside a GPU tensor moves it there with
`to_device`. A CUDA graph's capture cannot copy from the host, so while `device_copies` holds a
dict the same CPU tensor is copied once and its copy reused (the copy the graph's kernels read).
"""

from __future__ import annotations

import contextlib
import contextvars

import torch

__all__ = ["device_copies", "to_device"]

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
        copies[key] = (x, x.to(device))  # x kept: its id is not reused while the copy stands
    return copies[key][1]
