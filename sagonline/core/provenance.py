"""Content digests: what a cached stage or a reported number was computed from.

Every stage cache key and every run's metrics.json is built from these, so a number can be
traced to the exact bytes of its inputs: the scene's parameters, the cameras (intrinsics, pose,
size), the masks, the segmenter checkpoint. Digests are BLAKE2b-128 hex strings.

File digests are streamed and memoised by (path, size, mtime) in memory and in
`$SAGONLINE_DIGEST_CACHE` (default `~/.cache/sagonline/file_digests.json`), so a multi-GB
checkpoint is read once per change, not once per run.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import subprocess
import weakref
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch

_FILE_MEMO: dict[tuple[str, int, int], str] = {}
# Digests of sequences of read-only arrays, by the arrays' identities: a run digests the same
# ground truth for its record, its masks' cache key and (through the oracle) its masks.
_ARRAYS_MEMO: dict[tuple[int, ...], tuple[list[weakref.ref], str]] = {}
_MEMO_MIN_BYTES = 1 << 20


def _hasher():
    return hashlib.blake2b(digest_size=16)


def source_code(path: Path) -> bytes:
    """What a source file computes, for a digest that a comment or a docstring never moves:
    Python as its syntax tree without docstrings (`ast.dump`: no comments, no layout), C++ and
    headers without comments, trailing spaces and blank lines; any other file as its bytes."""
    if path.suffix not in (".py", ".cpp", ".h"):
        return path.read_bytes()
    text = path.read_text()
    if path.suffix == ".py":
        import ast

        tree = ast.parse(text, filename=str(path))
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if (
                isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
                and body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
        return ast.dump(tree).encode()
    import re

    # C++: a string or character literal is kept whole; a comment outside one is dropped
    literal_or_comment = r'("(?:\\.|[^"\\\n])*"|\'(?:\\.|[^\'\\\n])*\')|//[^\n]*|/\*.*?\*/'
    code = re.sub(literal_or_comment, lambda m: m.group(1) or " ", text, flags=re.S)
    lines = (line.rstrip() for line in code.splitlines())
    return "\n".join(line for line in lines if line).encode()


def digest_json(*parts) -> str:
    """Digest of JSON-able settings (keys sorted, so dict order never matters)."""
    blob = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.blake2b(blob.encode(), digest_size=16).hexdigest()


def _update_array(h, array, as_int64: bool = False) -> None:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().contiguous().numpy()
    array = np.ascontiguousarray(array)
    if as_int64 and array.dtype.kind in "iu" and array.dtype != np.int64 and array.size:
        # the bytes the values have as int64, a block of rows at a time (no int64 copy whole)
        h.update(f"{np.dtype(np.int64).str}{array.shape}".encode())
        rows = array.reshape(array.shape[0], -1) if array.ndim else array.reshape(1, 1)
        step = max(1, (1 << 20) // rows.shape[1])
        for start in range(0, len(rows), step):
            h.update(rows[start : start + step].astype(np.int64).view(np.uint8).reshape(-1).data)
        return
    h.update(f"{array.dtype.str}{array.shape}".encode())
    h.update(array.view(np.uint8).reshape(-1).data if array.size else b"")


def digest_arrays(arrays: Iterable, as_int64: bool = False) -> str:
    """Digest of a sequence of arrays/tensors: their dtypes, shapes and bytes (None allowed).
    A sequence of read-only NumPy arrays (the ground truth, `datasets.base.read_only`) is
    hashed once per process: the same arrays give their remembered digest. `as_int64`: integer
    arrays are hashed as their values in int64 (label maps, read at their files' 8 or 16 bits,
    keep the digests they had when they were read as int64)."""
    arrays = list(arrays)
    key = _frozen_key(arrays)
    if key is not None and as_int64:
        key = (*key, -1)
    if key is not None:
        hit = _ARRAYS_MEMO.get(key)
        if hit is not None and all(r() is a for r, a in zip(hit[0], arrays, strict=True)):
            return hit[1]
    h = _hasher()
    for a in arrays:
        if a is None:
            h.update(b"none")
        else:
            _update_array(h, a, as_int64)
    digest = h.hexdigest()
    if key is not None:
        if len(_ARRAYS_MEMO) >= 64:
            _ARRAYS_MEMO.clear()
        _ARRAYS_MEMO[key] = ([weakref.ref(a) for a in arrays], digest)
    return digest


def _frozen_key(arrays: list) -> tuple[int, ...] | None:
    """The identities of `arrays` when each is a NumPy array that nothing can change (it and
    every array it views are read-only) and they hold enough bytes to be worth remembering;
    else None."""
    total = 0
    for a in arrays:
        if not isinstance(a, np.ndarray):
            return None
        view = a
        while isinstance(view, np.ndarray):
            if view.flags.writeable:
                return None
            view = view.base
        total += a.nbytes
    return tuple(map(id, arrays)) if arrays and total >= _MEMO_MIN_BYTES else None


def digest_gaussians(gaussians) -> str:
    """Digest of a scene's parameters (kind and every activated tensor, on any device)."""
    fields = ("means", "quats", "scales", "opacities", "sh", "normals")
    h = _hasher()
    h.update(str(gaussians.kind).encode())
    h.update(digest_arrays(getattr(gaussians, f, None) for f in fields).encode())
    return h.hexdigest()


def digest_cameras(cameras) -> str:
    """Digest of cameras: name, size, intrinsics and pose of each, in order."""
    h = _hasher()
    for cam in cameras:
        h.update(f"{cam.name}|{cam.width}x{cam.height}".encode())
        _update_array(h, cam.K.float())
        _update_array(h, cam.world_to_cam.float())
    return h.hexdigest()


def _memo_path() -> Path:
    default = Path.home() / ".cache" / "sagonline" / "file_digests.json"
    return Path(os.environ.get("SAGONLINE_DIGEST_CACHE", default))


def _load_memo(path: Path) -> dict:
    try:
        memo = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return memo if isinstance(memo, dict) else {}


def _remember(disk_key: str, value: str) -> None:
    """Add one digest to the memo file: read, merge and write under an exclusive lock, so that
    processes digesting at once never drop each other's entries (best effort: a read-only home
    only costs a re-read next time)."""
    import fcntl

    from sagonline.core.files import atomic_write_text

    path = _memo_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path.with_suffix(".lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            memo = _load_memo(path)
            memo[disk_key] = value
            atomic_write_text(path, json.dumps(memo))
    except OSError:
        pass


def digest_file(path: str | Path) -> str:
    """Streamed digest of a file's bytes, memoised by (resolved path, device, inode, size,
    mtime_ns, ctime_ns) in this process and in a memo file (`SAGONLINE_DIGEST_CACHE`)."""
    path = Path(path).resolve()
    st = path.stat()
    key = (str(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    if key in _FILE_MEMO:
        return _FILE_MEMO[key]
    disk_key = "|".join(map(str, key))
    memo = _load_memo(_memo_path())
    if isinstance(memo.get(disk_key), str):
        _FILE_MEMO[key] = memo[disk_key]
        return memo[disk_key]
    h = _hasher()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    value = _FILE_MEMO[key] = h.hexdigest()
    _remember(disk_key, value)
    return value


@functools.cache
def _sha256_of(key: tuple) -> str:
    digest = hashlib.sha256()
    with open(key[0], "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    return digest.hexdigest()


def sha256_file(path: str | Path) -> str:
    """A file's SHA-256 (the digest a weights file is published with), memoised in this process
    by (resolved path, size, mtime_ns)."""
    path = Path(path).resolve()
    st = path.stat()
    return _sha256_of((str(path), st.st_size, st.st_mtime_ns, st.st_ino))


def digest_path(path: str | Path) -> str:
    """A file's digest, or a folder's: the names and digests of every file below it."""
    path = Path(path)
    if path.is_file():
        return digest_file(path)
    h = _hasher()
    for p in sorted(q for q in path.rglob("*") if q.is_file()):
        h.update(f"{p.relative_to(path)}={digest_file(p)}".encode())
    return h.hexdigest()


def git_state(repo: str | Path | None = None) -> dict:
    """The harness's commit and whether its working tree differs from it."""
    repo = Path(repo) if repo is not None else Path(__file__).resolve().parents[1]

    def git(*args) -> str | None:
        try:
            out = subprocess.run(
                ["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10
            )
        except (OSError, subprocess.TimeoutExpired):
            return None
        return out.stdout.strip() if out.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "dirty": None}
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "dirty": bool(status)}
