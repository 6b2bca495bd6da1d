"""Small shared helpers: atomic writes and the device description."""

from __future__ import annotations

import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np


def check_settings(group: str, **checks: tuple[bool, object, str]) -> None:
    """Raise ValueError `group.key=value: must be <rule>` for the first check that fails.
    checks: key -> (holds, value, rule), e.g. margin=(0 <= m < 1, m, "in [0, 1)")."""
    for key, (holds, value, rule) in checks.items():
        if not holds:
            raise ValueError(f"{group}.{key}={value!r}: must be {rule}")


def _umask() -> int:
    """The process umask, read without changing it where the OS says it (Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, write) -> Path:
    """Write `path` through `write(tmp_path)` into a temporary file beside it, then rename:
    readers never see a half-written file, and an interrupted write leaves the old one. The
    result gets the mode a plain `open` would give (0666 less the umask), not mkstemp's 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write(Path(path), lambda p: p.write_text(text))


def atomic_write_json(path: str | Path, obj) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def atomic_write_npy(path: str | Path, array: np.ndarray) -> Path:
    def write(p: Path) -> None:
        with open(p, "wb") as f:
            np.save(f, array)

    return atomic_write(Path(path), write)


def atomic_write_image(path: str | Path, image: np.ndarray) -> Path:
    """uint8 (H, W) or (H, W, 3) RGB to PNG/JPEG."""
    from PIL import Image

    fmt = {".jpg": "JPEG", ".jpeg": "JPEG"}.get(Path(path).suffix.lower(), "PNG")
    return atomic_write(Path(path), lambda p: Image.fromarray(image).save(p, format=fmt))


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


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
    }
    if hasattr(os, "getloadavg"):
        info["load_average_1m"] = round(os.getloadavg()[0], 2)
    if str(device).startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
