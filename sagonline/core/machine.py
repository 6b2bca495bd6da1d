"""Facts about the machine a run timed itself on (recorded beside every timing)."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def describe_device(device: str = "cpu") -> dict:
    """CPU model and cores, or GPU name; torch version; the 1-minute load average now (what
    else ran beside a timing: about the job's own threads when nothing else did)."""
    import torch

    info = {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cpu": _cpu_model(),
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cpu_capability": cpu_capability(),
    }
    if hasattr(os, "getloadavg"):
        info["load_average_1m"] = round(os.getloadavg()[0], 2)
    if str(device).startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def load_averages() -> str:
    """The system's load averages over 1, 5 and 15 minutes, as `uptime` shows them (what else
    ran beside a timing), from the kernel, without starting `uptime` (a slim system has none);
    "load average: -" where the system gives none."""
    if not hasattr(os, "getloadavg"):
        return "load average: -"
    return "load average: " + ", ".join(f"{load:.2f}" for load in os.getloadavg())


DEVICE_DEFAULT = "auto"
"""Every front end's device when none is given: `device=` (Hydra), `--device` (the commands),
`PipelineSettings.device`."""
DEVICE_HELP = "auto (cuda when available, else cpu), cpu, cuda or cuda:N"
# The renderer's and the vote's implementations by name (chosen per device in
# `render.backends`; named here, without PyTorch, for the commands' --help)
BACKENDS = ("torch", "native", "gsplat", "triton", "auto")
VOTE_BACKENDS = ("torch", "native", "triton", "gsplat", "auto")


def resolve_device(device) -> str:
    """'auto' -> 'cuda' when CUDA is available, else 'cpu'; any other name as given (a
    torch.device as its name). The one place 'auto' is resolved."""
    if str(device) == DEVICE_DEFAULT:
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return str(device)


def check_device(device: str) -> str:
    """`device` resolved (`resolve_device`) if it exists here; ValueError naming it otherwise
    (no CUDA, no such index, a name torch does not know)."""
    import torch

    device = resolve_device(device)
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device {device!r}: {exc}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device {device!r}: use cpu, cuda or cuda:N")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"device {device!r}: CUDA is not available here (torch {torch.__version__}); use cpu"
        )
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    return device


def cpu_capability() -> str:
    """The vector instruction set torch's CPU kernels run with (AVX512, AVX2, DEFAULT, ...)."""
    import torch

    try:
        return str(torch.backends.cpu.get_cpu_capability())
    except (AttributeError, RuntimeError):
        return "unknown"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
