"""Helpers of the tests that give the harness bad input: the one line an error must be, a
subprocess with its peak memory, hostile files (a PNG bomb, a pickle that runs code), a user's
scene folder and a generic capture."""

from __future__ import annotations

import pickle
import subprocess
import sys
import zlib
from pathlib import Path

import torch

from bench.runners.eval import evaluate
from tests.fixtures import (
    ROOT,
    compose_config,
    llff_scene,
    object_mask,
    own_scene,
    write_image,
)

NAMES = [f"IMG_{i:04d}" for i in range(5)]


class Planted:
    """A pickled object that writes a file when unpickled: what an attacker leaves in a cache."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "code ran"))


def plant(path: Path, marker: Path, how: str = "torch") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    value = {"model": Planted(marker), "state": Planted(marker)}
    if how == "torch":
        torch.save(value, path)
    else:
        path.write_bytes(pickle.dumps(value))
    return path


def generic_capture(root: Path) -> Path:
    cams, sc = llff_scene(root, NAMES)
    for cam, name in zip(cams, NAMES, strict=True):
        write_image(root / "masks" / f"{name}.png", object_mask(sc, cam) * 255)
    return root


def generic_cfg(root: Path, *overrides):
    """An evaluation of the generic capture at `root`, composed (no progress bars)."""
    return compose_config(
        "eval",
        *["dataset=generic", f"dataset.root={root}", "progress=false", *overrides],
    )


def eval_generic(root: Path, run: Path, *overrides):
    """The generic capture at `root` evaluated into `run`, without a recording or images."""
    cfg = generic_cfg(root, "record=false", "dataset.adapter.image_dir=null", *overrides)
    return evaluate(cfg, run)


def bomb_png(path: Path, width: int, height: int) -> Path:
    """A 1-bit PNG of width x height zeros: tens of kilobytes holding hundreds of millions of
    pixels once decoded."""
    import struct

    rows = b"".join(b"\x00" + b"\x00" * ((width + 7) // 8) for _ in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows, 9))
        + chunk(b"IEND", b"")
    )
    return path


def user_scene_files(folder: Path, views: int = 4, width: int = 40, height: int = 30):
    """`own_scene`'s folder, its point_cloud.ply, cameras and first view's ground truth."""
    folder, _, cams, gt = own_scene(folder, views=views, width=width, height=height)
    return folder, folder / "point_cloud.ply", cams, gt


def one_error_line(err: str, *words: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and "a bug" not in err, err
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


def run_python(*args: str, cwd=ROOT, env=None) -> tuple[int, str, int]:
    """A subprocess: its exit status, stderr, and its peak resident memory in MB (VmHWM: its own
    address space's; ru_maxrss carries over the forking pytest's peak across exec)."""
    code = (
        "import runpy, sys\n"
        f"sys.argv = {list(args)!r}\n"
        "try:\n"
        "    runpy.run_module(sys.argv[0], run_name='__main__', alter_sys=True)\n"
        "finally:\n"
        "    hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')]\n"
        "    peak = int(hwm[0].split()[1]) // 1024 if hwm else -1\n"
        "    print(f'PEAK_MB {peak}', file=sys.stderr)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300, env=env
    )
    lines = proc.stderr.strip().splitlines()
    peak = int(lines[-1].split()[1]) if lines and lines[-1].startswith("PEAK_MB") else -1
    return proc.returncode, "\n".join(lines[:-1]), peak


def error_line(capsys, *words) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err
    return err
