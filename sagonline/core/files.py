"""Files written whole or not at all, and JSON that other tools can read.

Every file the harness writes goes through `atomic_write`: a temporary file beside the target,
renamed into place, so a reader never sees half a file and an interrupted write leaves the old
one. JSON is strict (no NaN or Infinity, which are not JSON): a value that is not finite is
written as null, or refused where the caller says so.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np


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
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is None:  # a write through a file object: name the file it was for
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write(Path(path), lambda p: p.write_text(text))


def atomic_write_json(path: str | Path, obj) -> Path:
    """`obj` as strict JSON (`to_json`)."""
    return atomic_write_text(path, to_json(obj) + "\n")


def to_json(obj, indent: int | None = 2) -> str:
    """Strict JSON text: NumPy values and paths converted, NaN and +-Infinity written as null
    (they are not JSON: other tools refuse or misread them)."""
    return json.dumps(finite_tree(obj), indent=indent, default=_json_default, allow_nan=False)


def finite_tree(obj):
    """A copy of a JSON-like tree with every non-finite float replaced by None."""
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_tree(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_tree(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_tree(obj.tolist())
    return obj


def read_json_object(
    path: Path, error: type[Exception], unreadable: str = "not readable JSON", kind="an object"
) -> dict:
    """The JSON object in `path`; `error` naming the file when it cannot be read or parsed
    ("{path}: {unreadable} (why)") or holds something else ("{path}: holds a list, not {kind}")."""
    try:
        value = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise error(f"{path}: {unreadable} ({exc})") from None
    if not isinstance(value, dict):
        raise error(f"{path}: holds a {type(value).__name__}, not {kind}")
    return value


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
