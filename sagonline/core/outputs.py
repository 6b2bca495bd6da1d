"""One guard for everything a command writes: nothing already on disk is lost.

Every command (`render`, `segment`, `export`, `bench.runners.eval`, `bench.runners.scenes`) asks
here before it writes:
- an output may not equal, contain or sit inside any of the command's inputs: by path, by
  resolved path, or by hard link (`check_not_input`);
- `--overwrite` replaces only what the harness itself wrote, recognised by the manifest
  (`.sagonline-output.json`) it leaves in each output folder; any other folder is refused;
- a folder is built beside its target and swapped into place whole (`output_folder`), so the
  old output stays until the new one is complete, and an interrupted write leaves the old one;
- a run folder is locked while a run writes into it (`RunLock`), so a second run into the same
  folder is refused instead of interleaving its files with the first's.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import json
import os
import shutil
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from sagonline.core.files import atomic_write_json

MANIFEST = ".sagonline-output.json"


class OutputError(ValueError):
    """An output that may not be written where it was asked for; names the path and why."""


# --- inputs -----------------------------------------------------------------------------------


def check_not_input(out: str | Path, inputs: Iterable[str | Path], flag: str = "--out") -> None:
    """Refuse `out` when it is an input, holds one, or lies inside one (a folder input)."""
    out = Path(out)
    target = out.resolve()
    for given in inputs:
        path = Path(given)
        source = path.resolve()
        same = source == target or (_exists(out) and _exists(path) and _same_file(out, path))
        if same:
            raise OutputError(f"{flag} {out} is one of the inputs ({path}); choose another path")
        if source.is_relative_to(target):
            raise OutputError(
                f"{flag} {out} holds the input {path}: writing there could replace it; choose "
                "another path"
            )
        if path.is_dir() and target.is_relative_to(source):
            raise OutputError(f"{flag} {out} lies inside the input folder {path}; choose another")
        if _exists(out) and out.is_dir() and _links_to(out, path):
            raise OutputError(f"{flag} {out} holds a hard link of the input {path}")


def _exists(path: Path) -> bool:
    try:
        path.stat()
        return True
    except OSError:
        return False


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _links_to(folder: Path, path: Path, limit: int = 10_000) -> bool:
    """Whether a file below `folder` (a bounded walk) is `path` itself (a hard link of it)."""
    try:
        st = path.stat()
    except OSError:
        return False
    if path.is_dir() or st.st_nlink < 2:
        return False
    for i, candidate in enumerate(folder.rglob("*")):
        if i >= limit:
            break
        try:
            c = candidate.stat()
        except OSError:
            continue
        if (c.st_ino, c.st_dev) == (st.st_ino, st.st_dev):
            return True
    return False


# --- manifests --------------------------------------------------------------------------------


def is_ours(folder: str | Path) -> bool:
    """Whether `folder` is an output the harness wrote (its manifest is there and readable)."""
    manifest = Path(folder) / MANIFEST
    try:
        record = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and record.get("tool") == "sagonline"


def write_manifest(folder: Path, command: str, info: dict | None = None) -> None:
    """The manifest that makes `folder` recognisable as ours: the command, when, and what it
    holds (relative paths)."""
    files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    atomic_write_json(
        folder / MANIFEST,
        {
            "tool": "sagonline",
            "command": command,
            "written": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "files": files,
            **(info or {}),
        },
    )


def check_replaceable(out: Path, overwrite: bool, flag: str = "--out") -> None:
    """An existing `out` may be replaced only with `overwrite`, and only when it is a folder
    the harness wrote (its manifest says so)."""
    if not (_exists(out) or out.is_symlink()):
        return
    ours = out.is_dir() and not out.is_symlink() and is_ours(out)
    if not ours:
        kind = "a file" if out.is_file() else "a link" if out.is_symlink() else "a folder"
        raise OutputError(
            f"{flag} {out} is {kind} that sagonline did not write (no {MANIFEST}); it is never "
            "replaced: choose another path"
        )
    if not overwrite:
        raise OutputError(f"{flag} {out} holds an earlier output; pass --overwrite to replace it")


# --- writing a folder whole -------------------------------------------------------------------


@contextmanager
def output_folder(
    out: str | Path,
    *,
    inputs: Iterable[str | Path] = (),
    overwrite: bool = False,
    command: str = "",
    info: dict | None = None,
    flag: str = "--out",
) -> Iterator[Path]:
    """Build an output folder beside `out` and swap it into place once the block ends without
    an error (the manifest is written last). Yields the folder to write into. Refused first
    (OutputError) when `out` is an input, or exists and is not a replaceable earlier output."""
    out = Path(out)
    check_not_input(out, inputs, flag)
    check_replaceable(out, overwrite, flag)
    out.parent.mkdir(parents=True, exist_ok=True)
    clear_stale(out)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        write_manifest(tmp, command, info)
        carry_user_files(out, tmp)
        swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def carry_user_files(old: Path, new: Path) -> None:
    """Files a user added inside an earlier output (not in its manifest) go into its
    replacement too (hard links where the disk allows, so the earlier folder stays whole until
    the swap), under their own names, or NAME.yours where the new output has that name; they
    are named. The new manifest does not list them: they are not the harness's."""
    if not (old.is_dir() and is_ours(old)):
        return
    try:
        listed = set(json.loads((old / MANIFEST).read_text()).get("files") or [])
    except (OSError, ValueError, AttributeError):
        return
    carried = []
    for path in sorted(p for p in old.rglob("*") if p.is_file() and not p.is_symlink()):
        rel = path.relative_to(old).as_posix()
        if rel in listed or rel == MANIFEST:
            continue
        target = new / rel
        if target.exists():
            target = target.with_name(target.name + ".yours")
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)
        carried.append(target.relative_to(new).as_posix())
    if carried:
        import sys

        print(f"note: {old}: kept what you added there: {', '.join(carried)}", file=sys.stderr)


def swap_into_place(new: Path, out: Path) -> None:
    """Put the finished folder `new` at `out`. An existing `out` is exchanged with it in one
    atomic step where the system can (Linux renameat2), else renamed aside first; either way
    the old folder is removed only after the new one is in place."""
    if not out.exists():
        new.rename(out)
        return
    if _exchange(new, out):
        shutil.rmtree(new, ignore_errors=True)  # `new` now holds the old output
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    out.rename(old)
    new.rename(out)
    shutil.rmtree(old, ignore_errors=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (renameat2 with RENAME_EXCHANGE); False where unsupported."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    result = renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange)
    if result == 0:
        return True
    if ctypes.get_errno() in (errno.ENOSYS, errno.EINVAL, errno.EPERM, errno.EXDEV):
        return False
    raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()), str(b))


def clear_stale(out: Path) -> None:
    """Remove the hidden build and swap folders that killed writers of `out` left behind (their
    process is gone); another live writer's are left alone."""
    for leftover in out.parent.glob(f".{out.name}.*-*"):
        kind, _, pid = leftover.name.rpartition("-")
        if not (kind.endswith((".tmp", ".old")) and pid.isdigit()):
            continue
        if int(pid) != os.getpid() and not pid_alive(int(pid)):
            shutil.rmtree(leftover, ignore_errors=True)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# --- run folders ------------------------------------------------------------------------------


class RunLock:
    """An exclusive lock on a run folder while a run writes into it (`flock` on `.lock`,
    released by the system when the process ends, kill -9 included). A second run into the
    same folder is refused with OutputError instead of interleaving its files."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._fd: int | None = None

    def __enter__(self) -> RunLock:
        import fcntl

        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / ".lock"
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise OutputError(
                f"{self.folder}: another run is writing into this folder; wait for it, or "
                "choose another run folder"
            ) from None
        self._fd = fd  # the file stays empty: the folder's content never says who ran it
        return self

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing releases the lock
            self._fd = None


__all__ = [
    "MANIFEST",
    "OutputError",
    "RunLock",
    "check_not_input",
    "check_replaceable",
    "is_ours",
    "output_folder",
    "swap_into_place",
    "write_manifest",
]
