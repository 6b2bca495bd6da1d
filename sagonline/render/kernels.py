"""The compiled CPU kernels (csrc/): built once per Python environment, never a silent wait.

`load_extension` compiles them through torch's extension loader the first time (saying so, and
how long it took) into a folder of the environment itself (`kernel_root`), so checkouts with
environments of their own never rebuild each other's, nor do two paths to one environment (a
link to it: `build_name`). One process builds while the others
wait and say so (`build_once`); a build that was killed midway is noticed and its leftover
lock cleared, instead of every later run waiting on it forever. Every build runs the `ninja`
that the project's environment installed (`project_ninja`), whatever PATH finds first.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import sys
import time
from pathlib import Path

from sagonline.core.errors import NativeBuildError

CSRC = Path(__file__).parent / "csrc"
SOURCES = (CSRC / "raster_cpu.cpp", CSRC / "prepare_view.cpp", CSRC / "vote_cpu.cpp")
HEADERS = (CSRC / "splat_common.h",)


def kernel_root() -> Path:
    """Where the compiled kernels live: inside the Python environment (a virtual environment's
    own folder), or SAGONLINE_KERNEL_DIR; a Python whose prefix cannot be written uses the
    user's cache, one folder per prefix."""
    import hashlib

    chosen = os.environ.get("SAGONLINE_KERNEL_DIR")
    if chosen:
        if Path(chosen).exists() and not Path(chosen).is_dir():
            raise NativeBuildError(
                f"SAGONLINE_KERNEL_DIR={chosen} is a file: it must name a folder for the "
                "compiled kernels (or be unset)"
            )
        return Path(chosen)
    root = Path(sys.prefix) / "share" / "sagonline" / "kernels"
    try:
        root.mkdir(parents=True, exist_ok=True)
        if os.access(root, os.W_OK):
            return root
    except OSError:
        pass
    prefix = hashlib.blake2b(sys.prefix.encode(), digest_size=6).hexdigest()
    return Path.home() / ".cache" / "sagonline" / f"kernels-{prefix}"


@functools.cache
def load_extension():
    """Compile (once per environment) and import the C++ rasterizer and vote."""
    import logging

    # A CUDA build of PyTorch on a machine without a GPU warns at this import that it found no
    # CUDA runtime: nothing this CPU kernel needs, and a line before every command's own output.
    importing = logging.getLogger("torch.utils.cpp_extension")
    level = importing.level
    importing.setLevel(logging.ERROR)
    try:
        from torch.utils import cpp_extension
    finally:
        importing.setLevel(level)

    import torch

    name = build_name(Path(torch.__file__).parent)
    build_dir = kernel_root() / name

    def build():
        with project_ninja():
            return cpp_extension.load(**load_arguments(build_dir, name))

    try:
        return build_once(build_dir, name, build)
    except Exception as exc:  # compiler missing, ninja missing, build error
        raise NativeBuildError(f"could not build {CSRC}: {exc}") from exc


@contextlib.contextmanager
def project_ninja():
    """PATH with the folder of the `ninja` that the environment installed (the `ninja` package,
    a requirement of the project) first, put back after: torch's loader runs whichever `ninja`
    PATH finds. A machine without a system ninja then builds the kernels from a shell where the
    environment is not activated (`make install`, `.venv/bin/python -m ...`), where it failed
    ("Ninja is required") and every run fell back to the PyTorch reference; and where a system
    ninja of another version is there too, the two no longer rebuild the kernels in turn (each
    hashes the same compile command its own way, so each found it changed: 20-60 s a switch
    between an activated shell and one that is not). Without the package: PATH as it is."""
    try:
        from ninja import BIN_DIR as folder
    except ImportError:
        folder = None
    before = os.environ.get("PATH")
    if folder is None or shutil.which("ninja", path=folder) is None:
        yield
        return
    os.environ["PATH"] = os.pathsep.join([folder, before]) if before else folder
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PATH", None)
        else:
            os.environ["PATH"] = before


def build_name(torch_dir: Path) -> str:
    """The kernels' build folder's name. The source's digest is in it: each version of the
    kernel gets its own folder, so a build of another version is never loaded by mistake
    (torch's loader trusts file times, and a newer build of other source looks up to date).
    `torch_dir` is where this process imported PyTorch from: torch's compile command names it,
    so an environment reached through a link (a worktree's `.venv` linking to the checkout's)
    gets a folder of its own; sharing one, the two paths rebuilt each other's kernels in turn, a
    minute each time. Reached by its own path, the name is the source's digest alone."""
    import hashlib

    digest = hashlib.blake2b(digest_size=6)
    for path in SOURCES + HEADERS:
        digest.update(path.read_bytes())
    if torch_dir.resolve() != torch_dir.absolute():
        digest.update(str(torch_dir.absolute()).encode())
    return f"sagonline_raster_cpu_{digest.hexdigest()}"


def load_arguments(build_dir: Path, name: str) -> dict:
    """torch's `cpp_extension.load` arguments for the kernels, compiled from a copy of their
    sources inside `build_dir`: the loader rebuilds whenever its compile command changes, and
    with each checkout's own source paths in it, two checkouts sharing one environment (a clone
    beside the working tree) rebuilt the kernels in turn, a minute each time."""
    sources = copied_sources(build_dir / "src")
    return dict(
        name=name,
        sources=[str(sources / path.name) for path in SOURCES],
        extra_include_paths=[str(sources)],
        # no FMA contraction: the AVX2 and baseline builds of the vote (and x86 and ARM) then
        # run the same float operations
        extra_cflags=["-O3", "-fopenmp", "-ffp-contract=off", "-Wno-psabi"],
        extra_ldflags=["-fopenmp"],
        build_directory=str(build_dir),
        verbose=False,
    )


def copied_sources(folder: Path) -> Path:
    """The kernels' sources and headers copied into `folder` (each rewritten only where its
    bytes differ, so that a copy already there keeps the file time the build went by)."""
    from sagonline.core.files import atomic_write

    folder.mkdir(parents=True, exist_ok=True)
    for path in SOURCES + HEADERS:
        text, copy = path.read_bytes(), folder / path.name
        if not copy.is_file() or copy.read_bytes() != text:
            atomic_write(copy, lambda target, text=text: target.write_bytes(text))
    return folder


def library_digest(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def check_library(build_dir: Path, name: str, say) -> None:
    """A compiled library is loaded only when its bytes are those recorded when its build
    finished (`<name>.so.sha256`): a build killed while linking, a full disk or a damaged copy
    leaves a library that would kill the process with SIGBUS when loaded. Such a folder is
    emptied, said, and built again."""
    library, record = build_dir / f"{name}.so", build_dir / f"{name}.so.sha256"
    if not library.exists():
        return
    expected = record.read_text().strip() if record.is_file() else None
    if expected is not None and library_digest(library) == expected:
        return
    why = "no digest was recorded" if expected is None else "its bytes changed"
    say(
        f"the compiled CPU kernels in {build_dir} are not the build that finished ({why}): "
        "building them again"
    )
    for entry in build_dir.iterdir():
        if entry.is_file():
            entry.unlink(missing_ok=True)


def build_once(build_dir: Path, name: str, build, say=None, every: float = 20.0):
    """Run torch's loader `build()` for the extension `name` in `build_dir` under an exclusive
    lock of our own (`flock`, released by the system when its owner ends, kill -9 included):
    one process builds, the others wait for it and say so. Holding that lock, a `lock` file of
    torch's in the folder was left by a build that was killed: it is removed with a message
    instead of being waited on forever; a library whose digest is not the one recorded when its
    build finished is built again (`check_library`). A build says that it compiles, that it
    still does every `every` seconds, and how long it took."""
    import fcntl
    import threading

    say = say or (lambda text: print(text, file=sys.stderr, flush=True))
    build_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(build_dir.parent / f"{name}.build-lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            say(f"waiting for another process that is compiling the CPU kernels ({build_dir})")
            fcntl.flock(fd, fcntl.LOCK_EX)
        stale = build_dir / "lock"
        if stale.exists():
            say(f"removed {stale}: a build of the CPU kernels was killed before it finished")
            stale.unlink(missing_ok=True)
        check_library(build_dir, name, say)
        library = build_dir / f"{name}.so"
        fresh = not library.exists()
        done = threading.Event()
        start = time.perf_counter()
        if fresh:
            say("compiling the CPU kernels, one time for this environment (30-60 s on 2 cores) ...")

        # a library already there is built again only where torch's loader finds its compile
        # command changed (a new PyTorch, another build's flags)
        again = "" if fresh else " again (their compile command changed)"

        def heartbeat() -> None:
            while not done.wait(every):
                say(f"still compiling the CPU kernels{again} ({time.perf_counter() - start:.0f} s)")

        threading.Thread(target=heartbeat, daemon=True).start()
        try:
            module = build()
        finally:
            done.set()
        # recorded after every build, not only the first: where torch's loader built the library
        # again (a changed compile command), the next process would otherwise find bytes other
        # than those recorded and build a third time
        record = build_dir / f"{name}.so.sha256"
        if library.exists():
            digest = library_digest(library)
            if not record.is_file() or record.read_text().strip() != digest:
                from sagonline.core.files import atomic_write_text

                atomic_write_text(record, digest + "\n")
        took = time.perf_counter() - start
        if fresh or took >= every:
            say(f"compiled the CPU kernels in {took:.0f} s ({build_dir})")
        return module
    finally:
        os.close(fd)


__all__ = ["NativeBuildError", "build_once", "kernel_root", "load_extension", "project_ninja"]


# `make install`: build them now (or find them built), not at a first run
if __name__ == "__main__":
    try:
        load_extension()
    except NativeBuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
    print(f"the CPU kernels are built ({kernel_root()})")
