"""Which implementation renders and which votes, for a backend name and a device.

Renderers: torch (the readable twin), native (the compiled CPU kernel), gsplat (CUDA); auto
picks the compiled kernel on the CPU and gsplat on CUDA. The vote has one more, triton (the
fused GPU kernel), which auto prefers on CUDA.
"""

from __future__ import annotations

import torch

BACKENDS = ("torch", "native", "gsplat", "auto")
VOTE_BACKENDS = ("torch", "native", "triton", "gsplat")


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """'auto' picks gsplat on CUDA when installed, the compiled CPU kernel on the CPU when it
    builds, else the torch rasterizer."""
    if backend not in BACKENDS:
        raise ValueError(f"renderer backend {backend!r} is not one of {BACKENDS}")
    if backend == "gsplat" and torch.device(device).type != "cuda":
        raise ValueError(
            f"renderer backend 'gsplat' runs on CUDA only (device {device}); on the CPU use "
            "native, torch or auto"
        )
    if backend == "auto":
        if torch.device(device).type == "cuda":
            from sagonline.render.gsplat_backend import gsplat_available

            return "gsplat" if gsplat_available() else "torch"
        from sagonline.render.native import native_available

        return "native" if native_available() else "torch"
    return backend


def resolve_vote_backend(backend: str, device: torch.device | str) -> str:
    """The vote implementation for a renderer backend: 'auto' takes the fastest one the device
    has (CPU: native; CUDA: triton, else gsplat), 'gsplat' on CUDA prefers the fused Triton
    kernel when Triton is installed; 'torch', 'native' and 'triton' are taken as asked."""
    if backend == "triton":
        return backend
    if backend not in ("auto", "gsplat"):
        return resolve_backend(backend, device)
    if torch.device(device).type == "cuda":
        from sagonline.render.triton_vote import triton_available

        if triton_available():
            return "triton"
    return resolve_backend(backend, device)
