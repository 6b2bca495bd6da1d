"""Which implementation renders and which votes, for a backend name and a device.

Image renderers: torch (the readable twin, CPU or CUDA), native (the compiled CPU kernel),
gsplat (CUDA) and triton (the fused walk's composite, CUDA, no gradients; its interpreter runs
it on the CPU when asked for by name). The vote and the label renders have the same four.
'auto' takes the fastest one the device has, for images and for the vote each on its own:

| device | images (auto)                     | vote and label renders (auto)     |
|--------|-----------------------------------|-----------------------------------|
| cpu    | native, else torch                | native, else torch                |
| cuda   | gsplat, else triton, else torch   | triton, else gsplat, else torch   |

A render that needs gradients (the fit) never runs on triton: `render.api.render` takes the
PyTorch twin instead.

What is installed is asked through an `Installed` (`installed()` probes this machine, lazily:
the compiled kernel is built only when the CPU resolution needs it), so every branch,
the CUDA ones included, is a plain function of (name, device, what is installed) that runs and
is tested on any machine: building `torch.device("cuda")` needs no GPU.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from sagonline.core.machine import BACKENDS, VOTE_BACKENDS, resolve_device
from sagonline.core.provenance import source_code

DEVICES = ("cpu", "cuda", "cuda:N", "auto")

# What to install for a backend that is not there, named in every refusal.
EXTRA = {
    "gsplat": "pip install -e '.[gsplat]' (CUDA only)",
    "triton": "pip install -e '.[triton]'",
    "native": "a C++ compiler and ninja (pip install ninja)",
}


class BackendError(ValueError):
    """A backend that cannot run on this device or is not installed: says which and why."""


def _has_module(name: str) -> bool:
    """Whether `name` can be imported; SAGONLINE_WITHOUT=gsplat,triton hides installed ones (a
    run as on a machine without them, beside one with them: scripts/gpu_check.sh)."""
    hidden = {n.strip() for n in os.environ.get("SAGONLINE_WITHOUT", "").split(",")}
    return name not in hidden and importlib.util.find_spec(name) is not None


def _native_builds() -> bool:
    from sagonline.render.native import native_available

    return native_available()


@dataclass
class Installed:
    """What this machine has, each probed once on first use: CUDA, the gsplat and triton
    packages, and whether the compiled CPU kernel builds. Tests pass their own values."""

    cuda: bool | None = None
    gsplat: bool | None = None
    triton: bool | None = None
    native: bool | None = None
    _probes: dict = field(
        default_factory=lambda: {
            "cuda": torch.cuda.is_available,
            "gsplat": lambda: _has_module("gsplat"),
            "triton": lambda: _has_module("triton"),
            "native": _native_builds,
        },
        repr=False,
    )

    def has(self, what: str) -> bool:
        value = getattr(self, what)
        if value is None:
            value = bool(self._probes[what]())
            setattr(self, what, value)
        return value


@functools.cache
def installed() -> Installed:
    """This machine's `Installed`, probed lazily and once per process."""
    return Installed()


def _device_type(device: torch.device | str) -> str:
    return torch.device(resolve_device(device)).type


def resolve_backend(backend: str, device: torch.device | str, have: Installed | None = None) -> str:
    """The image renderer for `backend` on `device` (see the module's table); a backend that
    cannot run there, or is not installed, is refused naming what to use or install."""
    have = have or installed()
    if backend not in BACKENDS:
        raise BackendError(f"renderer backend {backend!r} is not one of {BACKENDS}")
    on_cuda = _device_type(device) == "cuda"
    if backend == "gsplat" and not on_cuda:
        raise BackendError(
            f"renderer backend 'gsplat' runs on CUDA only (device {device}); on the CPU use "
            "native, torch or auto"
        )
    if backend == "native" and on_cuda:
        raise BackendError(
            f"renderer backend 'native' is the compiled CPU kernel (device {device}); on CUDA "
            "use auto, gsplat or torch"
        )
    if backend in ("gsplat", "triton") and not have.has(backend):
        raise BackendError(f"renderer backend {backend!r} is not installed: {EXTRA[backend]}")
    if backend != "auto":
        return backend
    if on_cuda:
        for fast in ("gsplat", "triton"):
            if have.has(fast):
                return fast
        return "torch"
    return "native" if have.has("native") else "torch"


def resolve_vote_backend(
    backend: str, device: torch.device | str, have: Installed | None = None
) -> str:
    """The vote's (and the label renders') implementation for `backend` on `device`, resolved
    on its own, never from the image renderer's choice: 'auto' takes the fastest the device
    has (see the module's table); a named one is taken as asked, or refused when it cannot
    run there or is not installed (triton on the CPU runs in Triton's interpreter)."""
    have = have or installed()
    if backend not in VOTE_BACKENDS:
        raise BackendError(f"vote backend {backend!r} is not one of {VOTE_BACKENDS}")
    on_cuda = _device_type(device) == "cuda"
    if backend in ("triton", "gsplat") and not have.has(backend):
        raise BackendError(f"vote backend {backend!r} is not installed: {EXTRA[backend]}")
    if backend == "gsplat" and not on_cuda:
        raise BackendError(f"vote backend 'gsplat' runs on CUDA only (device {device})")
    if backend == "native" and on_cuda:
        raise BackendError(
            f"vote backend 'native' is the compiled CPU kernel (device {device}); on CUDA use "
            "auto, triton or torch"
        )
    if backend != "auto":
        return backend
    if on_cuda:
        for fast in ("triton", "gsplat"):
            if have.has(fast):
                return fast
        return "torch"
    return "native" if have.has("native") else "torch"


@dataclass(frozen=True)
class BackendPlan:
    """What each stage of a run uses, resolved once before any work: images (the trajectory
    frames, the recorded renders), the vote, and the label renders that scoring reads."""

    device: str
    images: str
    vote: str
    labels: str

    def describe(self) -> dict[str, str]:
        return {
            "device": self.device,
            "images": self.images,
            "vote": self.vote,
            "labels": self.labels,
        }


def plan_backends(
    images: str, vote: str, device: torch.device | str, have: Installed | None = None
) -> BackendPlan:
    """Resolve a run's image and vote backends (each its own setting) for `device` ('auto'
    included): the label renders take the vote's walk (`render.api.render_labels`)."""
    have = have or installed()
    dev = resolve_device(device)
    chosen_vote = resolve_vote_backend(vote, dev, have)
    return BackendPlan(dev, resolve_backend(images, dev, have), chosen_vote, chosen_vote)


# The source files each implementation's results depend on (its own and what it calls).
_HERE = Path(__file__).parent
_SOURCES = {
    "torch": ("_torch_impl.py", "rasterize.py", "projection.py", "sh.py"),
    "native": (
        "native.py",
        "projection.py",
        "rasterize.py",
        "csrc/raster_cpu.cpp",
        "csrc/prepare_view.cpp",
        "csrc/vote_cpu.cpp",
        "csrc/splat_common.h",
    ),
    "triton": (
        "triton_vote.py",
        "triton_vote_chunk.py",
        "triton_composite.py",
        "triton_prepare.py",
        "projection.py",
        "rasterize.py",
    ),
    "gsplat": ("gsplat_backend.py", "_torch_impl.py", "projection.py", "rasterize.py", "sh.py"),
}


# The Triton vote's kernels: (splats a step of its loop takes, warps per tile) (0: the splat
# walk, one splat on 4 warps): `walk` (triton_vote) and `chunk16`, `chunk32` and `chunk16w16`
# (triton_vote_chunk on 8 or 16 warps: the compiler gives it one block an SM at 8 warps,
# `bench.speed.kernel_resources`). SAGONLINE_TRITON_VOTE chooses one, read at each vote, so that
# a benchmark times them side by side in one process (bench/speed/vote_kernels.py); unset, the
# rule's default (`DEFAULT_TRITON_VOTE`).
TRITON_VOTE_KERNELS = {
    "walk": (0, 4),
    "chunk16": (16, 8),
    "chunk32": (32, 8),
    "chunk16w16": (16, 16),
}


# Unset, the vote kernel by the rule's weighting where CUDA is: `chunk16` counts, on two H200
# leases 1.81 and 1.91 ms a vote against the walk's 2.65 and 2.54 (round three), 1.88 and 1.86
# against 3.10 and 2.48 (round two), with the walk's votes (reports/cuda_2026-12-04b/
# vote_kernels_cuda.csv); its blend variant spills registers and was never timed, so blends
# walk. On the CPU (Triton's interpreter, the tests) the walk.
# The chunked votes hold a tile's (256 pixels, labels) one-hot block in shared memory: 132 KB at
# 256 labels, 263 KB at 512, past an sm_90 SM's 228 KB (`bench.speed.kernel_resources`), so more
# labels than CHUNKED_MAX_LABELS walk (and naming a chunked vote for them is refused).
DEFAULT_TRITON_VOTE = {"count": "chunk16", "blend": "walk"}
CHUNKED_MAX_LABELS = 256


def triton_vote_kernel(weighting: str | None = None, num_labels: int = 0) -> str:
    """The Triton vote kernel this process launches for a rule of `weighting` (count, blend)
    over `num_labels` labels: SAGONLINE_TRITON_VOTE where it is set, else `DEFAULT_TRITON_VOTE`
    where CUDA is (the walk past `CHUNKED_MAX_LABELS`) and the walk on the CPU; weighting None:
    the setting as text (`auto` where unset: by the rule)."""
    name = os.environ.get("SAGONLINE_TRITON_VOTE")
    if not name:
        if weighting is None:
            return "auto"
        if not torch.cuda.is_available() or num_labels > CHUNKED_MAX_LABELS:
            return "walk"
        return DEFAULT_TRITON_VOTE[weighting]
    if name not in TRITON_VOTE_KERNELS:
        raise BackendError(
            f"SAGONLINE_TRITON_VOTE={name!r}: use one of {tuple(TRITON_VOTE_KERNELS)}"
        )
    if TRITON_VOTE_KERNELS[name][0] and num_labels > CHUNKED_MAX_LABELS:
        raise BackendError(
            f"SAGONLINE_TRITON_VOTE={name}: a chunked vote holds at most {CHUNKED_MAX_LABELS} "
            f"labels (a tile's one-hot block in shared memory), this vote has {num_labels}; "
            "unset it (the walk takes these) or set walk"
        )
    return name


# How the Triton walks' tile lists are made (SAGONLINE_TRITON_PREPARE, read at each view):
# `torch` (`projection.project` and `rasterize.bin_tiles`, a chain of small PyTorch operators)
# or `fused` (`triton_prepare`: two kernels and a sort). bench/speed/vote_kernels.py times both:
# on an H200 the fused lists took 1.07 and 0.88 ms against 3.14 and 3.51 ms, and the walk's
# vote 3.10 and 2.48 ms against 5.09 and 5.47 ms on the two bench scenes
# (reports/cuda_2026-12-04/vote_kernels_cuda.csv), so `fused` is the default where CUDA is; on
# the CPU (Triton's interpreter, the tests) `torch` stays the default.
TRITON_PREPARES = ("torch", "fused")


def triton_prepare() -> str:
    """How this process's Triton walks project and bin a view (SAGONLINE_TRITON_PREPARE;
    default fused where CUDA is available, else torch)."""
    default = "fused" if torch.cuda.is_available() else "torch"
    name = os.environ.get("SAGONLINE_TRITON_PREPARE") or default
    if name not in TRITON_PREPARES:
        raise BackendError(f"SAGONLINE_TRITON_PREPARE={name!r}: use one of {TRITON_PREPARES}")
    return name


def implementation_digest(backend: str) -> str:
    """A digest of what a resolved backend computes with: its source files (kernels included),
    for gsplat and triton the installed package's version, and for triton which of its vote
    kernels runs (SAGONLINE_TRITON_VOTE) and how it bins a view (SAGONLINE_TRITON_PREPARE);
    part of every cache key that a render or a vote produced, so a changed kernel never
    reuses an old entry."""
    kernel = ""
    if backend == "triton":
        prepare = triton_prepare()
        kernel = triton_vote_kernel() + ("" if prepare == "torch" else f"+{prepare}")
    return _implementation_digest(backend, kernel)


@functools.cache
def _implementation_digest(backend: str, kernel: str) -> str:
    import hashlib

    if backend not in _SOURCES:
        raise BackendError(f"no implementation named {backend!r}")
    digest = hashlib.blake2b(backend.encode(), digest_size=8)
    for name in _SOURCES[backend]:  # their code: a comment or a docstring keys nothing apart
        digest.update(source_code(_HERE / name))
    if backend in ("gsplat", "triton"):
        from importlib.metadata import PackageNotFoundError, version

        with contextlib.suppress(PackageNotFoundError):
            digest.update(version(backend).encode())
    if kernel not in ("", "walk"):  # the walk keeps the digest of before the kernels were a choice
        digest.update(kernel.encode())
    return digest.hexdigest()
