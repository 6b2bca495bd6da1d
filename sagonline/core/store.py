"""The files the harness writes and reads back (stage caches, fit and student checkpoints).

Nothing in them can execute: a file holds a JSON tree (numbers, strings, lists, dicts with any
JSON-able keys, registered dataclasses) and raw arrays, never a pickle. Each file carries the
SHA-256 digest of its own bytes, checked before anything in it is decoded, so a damaged file
is refused whole (`StoreError` names it) instead of being read as wrong numbers or as a huge
allocation. Files of the first format (`SAGOST01`) carry BLAKE2b-256 instead and still load.
SHA-256 took its place because CPUs compute it in hardware (the SHA extensions): the check of a
SAM 2 embedding's 8.4 MB took 6.4 ms here against 17.7, and a cached embedding is read on every
view of a warm run (`bench.speed.sam_host`, "cache entry read").

Layout, little-endian:
    MAGIC (8 bytes) | digest (32 bytes, of everything after it) | header length (8 bytes) |
    header (JSON: {"tree": ..., "arrays": [{"dtype", "shape", "offset", "nbytes"}, ...]}) |
    array bytes (each at its offset from the start of this section)
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib
import json
import math
import struct
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from sagonline.core.files import atomic_write

MAGIC = b"SAGOST02"  # what `save` writes
DIGESTS = {  # each format's digest of the bytes after it, by its magic
    MAGIC: hashlib.sha256,
    b"SAGOST01": functools.partial(hashlib.blake2b, digest_size=32),
}
SUFFIX = ".store"
_DIGEST = 32
_PREFIX = len(MAGIC) + _DIGEST + 8
_KINDS = "biuf"  # bool, signed, unsigned, float: the only array kinds a file may hold

_DATACLASSES: dict[str, type] = {}
# The modules whose @stored dataclasses a file may hold: imported (when not yet) before a name
# is looked up, so loading never depends on what the caller happened to import. No other
# module is ever imported on behalf of a file.
STORED_MODULES = ("sagonline.vote.consensus", "sagonline.segment.base", "sagonline.pipeline.stages")


class StoreError(ValueError):
    """A stored file is missing, damaged, or not one of ours; the message names the file."""


def stored(cls: type) -> type:
    """Class decorator: a dataclass that may appear in a stored tree (looked up by this name on
    load; nothing else is ever constructed from a file)."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls.__name__} is not a dataclass")
    _DATACLASSES[f"{cls.__module__}.{cls.__qualname__}"] = cls
    return cls


# --- encode -----------------------------------------------------------------------------------


class _Encoder:
    def __init__(self) -> None:
        self.arrays: list[np.ndarray] = []
        self.meta: list[dict] = []

    def array(self, a: np.ndarray, torch_dtype: str | None) -> dict:
        a = np.ascontiguousarray(a)
        if a.dtype.kind not in _KINDS:
            raise TypeError(f"arrays of dtype {a.dtype} cannot be stored")
        offset = sum(m["nbytes"] for m in self.meta)
        self.meta.append(
            {"dtype": a.dtype.str, "shape": list(a.shape), "offset": offset, "nbytes": a.nbytes}
        )
        self.arrays.append(a)
        node = {"$": "tensor" if torch_dtype else "ndarray", "i": len(self.arrays) - 1}
        return node | ({"torch_dtype": torch_dtype} if torch_dtype else {})

    def tree(self, value: Any) -> Any:
        if value is None or isinstance(value, (bool, str)):
            return value
        if isinstance(value, (int, np.integer)):
            return int(value)
        if isinstance(value, (float, np.floating)):
            v = float(value)
            return v if math.isfinite(v) else {"$": "float", "v": repr(v)}
        if is_tensor(value):
            import torch

            t = value.detach().cpu().contiguous()
            if t.dtype == torch.bfloat16:
                return self.array(t.view(torch.int16).numpy(), "bfloat16")
            return self.array(t.numpy(), str(t.dtype).removeprefix("torch."))
        if isinstance(value, np.ndarray):
            return self.array(value, None)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            name = f"{type(value).__module__}.{type(value).__qualname__}"
            if name not in _DATACLASSES:
                raise TypeError(f"{name} is not registered with @stored")
            fields = {f.name: self.tree(getattr(value, f.name)) for f in dataclasses.fields(value)}
            return {"$": "dataclass", "name": name, "fields": fields}
        if isinstance(value, dict):
            return {"$": "dict", "items": [[self.tree(k), self.tree(v)] for k, v in value.items()]}
        if isinstance(value, (list, tuple, set, frozenset)):
            kind = type(value).__name__ if isinstance(value, (tuple, set, frozenset)) else "list"
            items = sorted(value, key=repr) if isinstance(value, (set, frozenset)) else value
            return {"$": kind, "items": [self.tree(v) for v in items]}
        raise TypeError(f"values of type {type(value).__name__} cannot be stored")


def save(path: str | Path, value: Any) -> Path:
    """Write `value` (tensors, arrays, JSON-able values, lists, tuples, dicts, sets and @stored
    dataclasses, nested) to `path` atomically. Tensors come back on the CPU."""
    enc = _Encoder()
    header = json.dumps({"tree": enc.tree(value), "arrays": enc.meta}).encode()
    h = DIGESTS[MAGIC]()
    length = struct.pack("<Q", len(header))
    payload = [a.reshape(-1).view(np.uint8) for a in enc.arrays]
    for part in (length, header, *payload):
        h.update(part)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(MAGIC + h.digest() + length + header)
            for part in payload:
                f.write(part)

    return atomic_write(path, write)


# --- decode -----------------------------------------------------------------------------------


def load(path: str | Path) -> Any:
    """Read a file written by `save`. Raises StoreError naming the file when it is missing,
    not ours (e.g. a pickle), truncated, or when any byte differs from what was written."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size < _PREFIX:
            raise StoreError(f"{path}: {size} bytes is too short to be a stored file")
        buf = bytearray(size)
        with open(path, "rb") as f:
            if f.readinto(buf) != size:
                raise StoreError(f"{path}: changed size while being read")
    except OSError as exc:
        raise StoreError(f"{path}: cannot be read ({exc})") from exc
    view = memoryview(buf)
    hasher = DIGESTS.get(bytes(view[: len(MAGIC)]))
    if hasher is None:
        raise StoreError(
            f"{path}: not a file the harness wrote (no {MAGIC.decode()} header; a pickle or other "
            "format is never loaded)"
        )
    digest = hasher(view[len(MAGIC) + _DIGEST :]).digest()
    if digest != bytes(view[len(MAGIC) : len(MAGIC) + _DIGEST]):
        raise StoreError(f"{path}: its bytes do not match their recorded digest (damaged)")
    (hlen,) = struct.unpack_from("<Q", buf, len(MAGIC) + _DIGEST)
    if _PREFIX + hlen > size:
        raise StoreError(f"{path}: header length {hlen} runs past the end of the file")
    try:
        header = json.loads(bytes(view[_PREFIX : _PREFIX + hlen]))
        arrays = [_array(view[_PREFIX + hlen :], m) for m in header["arrays"]]
        return _Decoder(arrays).tree(header["tree"])
    except StoreError as exc:
        raise StoreError(f"{path}: {exc}") from None
    except (ValueError, TypeError, KeyError, IndexError) as exc:
        raise StoreError(f"{path}: malformed contents ({type(exc).__name__}: {exc})") from exc


def load_or_discard(path: str | Path, what: str) -> Any | None:
    """`load(path)`, or None when the file is absent; a damaged or foreign file is named in a
    warning (`what` says what it was for), removed, and None returned, so the caller computes
    it again."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        return load(path)
    except StoreError as exc:
        warnings.warn(f"{what} unusable, removed and recomputed: {exc}", stacklevel=2)
        path.unlink(missing_ok=True)
        return None


def _array(payload: memoryview, meta: dict) -> np.ndarray:
    dtype = np.dtype(meta["dtype"])
    shape = tuple(int(s) for s in meta["shape"])
    offset, nbytes = int(meta["offset"]), int(meta["nbytes"])
    if dtype.kind not in _KINDS or any(s < 0 for s in shape):
        raise StoreError(f"array of dtype {dtype} and shape {shape} is not allowed")
    if math.prod(shape) * dtype.itemsize != nbytes or offset < 0 or offset + nbytes > len(payload):
        raise StoreError(f"array {shape} {dtype} does not fit its {nbytes} bytes at {offset}")
    return np.frombuffer(payload[offset : offset + nbytes], dtype=dtype).reshape(shape)


def is_tensor(value: Any) -> bool:
    """Whether `value` is a PyTorch tensor, asked without importing PyTorch (a tensor exists only
    once it is imported; the stored format itself never needs it)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(value, torch.Tensor)


class _Decoder:
    def __init__(self, arrays: list[np.ndarray]) -> None:
        self.arrays = arrays

    def tree(self, node: Any) -> Any:
        if not isinstance(node, dict):
            if isinstance(node, list):
                raise StoreError("untagged list in the tree")
            return node
        kind = node["$"]
        if kind == "float":
            return float(node["v"])
        if kind == "ndarray":
            return self.arrays[node["i"]]
        if kind == "tensor":
            import torch

            a = self.arrays[node["i"]]
            if node["torch_dtype"] == "bfloat16":
                return torch.from_numpy(a).view(torch.bfloat16)
            return torch.from_numpy(a)
        if kind == "dict":
            return {self._key(k): self.tree(v) for k, v in node["items"]}
        if kind in ("list", "tuple", "set", "frozenset"):
            items = [self.tree(v) for v in node["items"]]
            return {"list": list, "tuple": tuple, "set": set, "frozenset": frozenset}[kind](items)
        if kind == "dataclass":
            if node["name"] not in _DATACLASSES:
                for module in STORED_MODULES:
                    importlib.import_module(module)
            cls = _DATACLASSES.get(node["name"])
            if cls is None:
                raise StoreError(f"unknown type {node['name']!r} (not a stored dataclass)")
            return cls(**{k: self.tree(v) for k, v in node["fields"].items()})
        raise StoreError(f"unknown node kind {kind!r}")

    def _key(self, node: Any) -> Any:
        key = self.tree(node)
        return tuple(key) if isinstance(key, list) else key
