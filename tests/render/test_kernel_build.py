"""The compiled kernels: a truncated library is built again, not loaded."""

from __future__ import annotations

from pathlib import Path


def test_a_truncated_kernel_library_is_built_again_not_loaded(tmp_path):
    """A truncated library in the kernels folder killed every later render with SIGBUS and no
    word: its bytes are checked against the digest its finished build recorded, and a library
    that differs is removed and built again before anything loads it."""
    from sagonline.render.kernels import build_once, library_digest

    folder, said, built = tmp_path / "kernels" / "build", [], []

    def build():  # stands in for torch's loader: compiles when the library is absent
        library = folder / "k.so"
        built.append(library.exists())
        if not library.exists():
            library.write_bytes(b"\x7fELF" + b"\x00" * 8000)
        return library.read_bytes()

    build_once(folder, "k", build, say=said.append)  # a first build records its digest
    good = (folder / "k.so").read_bytes()
    assert (folder / "k.so.sha256").read_text().strip() == library_digest(folder / "k.so")
    (folder / "k.so").write_bytes(good[:4096])  # a build killed while linking
    assert build_once(folder, "k", build, say=said.append) == good
    assert built == [False, False]  # the truncated library was never handed to the loader
    assert any("not the build that finished (its bytes changed)" in s for s in said), said
    build_once(folder, "k", build, say=said.append)  # an intact library is loaded as it is
    assert built == [False, False, True]


CUDA_BUILD_WITHOUT_A_GPU = """
import os, sys, torch
os.environ["CUDA_HOME"] = sys.argv[1]  # a CUDA build of PyTorch that finds a toolkit, no GPU
torch.cuda._is_compiled = lambda: True
torch.cuda.is_available = lambda: False
torch.version.cuda = "13.0"
if sys.argv[2] == "kernel":
    from sagonline.render.kernels import load_extension
    load_extension()
else:
    from torch.utils import cpp_extension
"""


def test_loading_the_cpu_kernel_under_a_cuda_build_without_a_gpu_prints_nothing(tmp_path):
    """PyTorch's extension loader, imported under a CUDA build on a machine without a GPU,
    warns that it found no CUDA runtime: a line before every command's own output (and before
    the one-line refusals). Loading the CPU kernel keeps it quiet; imported plainly, it warns."""
    import subprocess
    import sys

    from tests.fixtures import ROOT

    def stderr(how: str) -> str:
        command = [sys.executable, "-c", CUDA_BUILD_WITHOUT_A_GPU, str(tmp_path), how]
        return subprocess.run(command, cwd=ROOT, capture_output=True, text=True).stderr

    assert "No CUDA runtime is found" in stderr("plainly")
    assert "No CUDA runtime is found" not in stderr("kernel")


def test_a_library_the_loader_built_again_is_recorded_not_built_a_third_time(tmp_path):
    """Where torch's loader builds the library again in a folder that had one (its compile
    command changed), the new bytes are recorded: the next process loads them instead of
    finding bytes other than those recorded and building once more. A rebuild that takes a
    while is said, as a first build is."""
    import time

    from sagonline.render.kernels import build_once, library_digest

    folder, said, built = tmp_path / "kernels" / "build", [], []

    def build():  # torch's loader, whose compile command changed after the first build
        library = folder / "k.so"
        built.append(library.exists())
        if len(built) == 2:
            time.sleep(0.5)  # compiling again
        library.write_bytes(b"\x7fELF" + bytes([len(built)]) * 8000)
        return library.read_bytes()

    build_once(folder, "k", build, say=said.append, every=0.2)
    first = len(said)
    build_once(folder, "k", build, say=said.append, every=0.2)  # rebuilt by the loader
    assert (folder / "k.so.sha256").read_text().strip() == library_digest(folder / "k.so")
    assert any("still compiling the CPU kernels again" in s for s in said[first:]), said
    assert said[-1].startswith("compiled the CPU kernels in")
    again = len(said)
    build_once(folder, "k", build, say=said.append, every=0.2)
    assert built == [False, True, True]  # never emptied and built from nothing again
    assert not any("not the build that finished" in s for s in said), said
    assert len(said) == again  # a library loaded at once: nothing said


def test_the_kernels_compile_from_a_copy_of_their_sources_in_the_build_folder(tmp_path):
    """The loader's arguments name copies of the sources inside the build folder, the same for
    every checkout, so two checkouts sharing an environment do not rebuild in turn; a copy
    already there is left as it is (its file time is what the build goes by), a changed one
    rewritten."""
    from sagonline.render.kernels import CSRC, HEADERS, SOURCES, load_arguments

    build_dir = tmp_path / "sagonline_raster_cpu_x"
    arguments = load_arguments(build_dir, "sagonline_raster_cpu_x")
    copies = build_dir / "src"
    assert arguments["sources"] == [str(copies / p.name) for p in SOURCES]
    assert arguments["extra_include_paths"] == [str(copies)]
    assert arguments["build_directory"] == str(build_dir)
    for path in SOURCES + HEADERS:
        assert (copies / path.name).read_bytes() == path.read_bytes()
    assert str(CSRC) not in repr(arguments)
    header = copies / HEADERS[0].name
    before = header.stat().st_mtime_ns
    vote_source = copies / SOURCES[-1].name
    vote_source.write_text("// damaged\n")
    assert load_arguments(build_dir, "sagonline_raster_cpu_x") == arguments
    assert header.stat().st_mtime_ns == before
    assert vote_source.read_bytes() == SOURCES[-1].read_bytes()


def test_an_environment_reached_through_a_link_builds_in_a_folder_of_its_own(tmp_path):
    """torch's compile command names the path PyTorch was imported from: a worktree whose
    `.venv` links to the checkout's shared the checkout's build folder under another command,
    and the two rebuilt the kernels in turn, a minute each time. Through a link the folder's
    name differs; through the environment's own path it is the sources' digest alone, as
    before."""
    import hashlib

    import torch

    from sagonline.render.kernels import HEADERS, SOURCES, build_name

    torch_dir = Path(torch.__file__).parent.resolve()
    digest = hashlib.blake2b(digest_size=6)
    for path in SOURCES + HEADERS:
        digest.update(path.read_bytes())
    assert build_name(torch_dir) == f"sagonline_raster_cpu_{digest.hexdigest()}"
    (tmp_path / "one").symlink_to(torch_dir.parent)
    (tmp_path / "two").symlink_to(torch_dir.parent)
    linked = [build_name(tmp_path / link / torch_dir.name) for link in ("one", "two")]
    assert len({build_name(torch_dir), *linked}) == 3
    assert build_name(tmp_path / "one" / torch_dir.name) == linked[0]  # the same path, the same


def test_the_build_benchmark_puts_back_the_header_the_kernels_included_before(
    tmp_path, monkeypatch
):
    """`bench.speed.kernel_build` compiles the kernels as written and with torch/extension.h:
    the second differs from the first in the two include lines alone (so the table compares
    the headers, nothing else), a source whose includes changed is refused by name, and each
    build's seconds land in the row of its variant."""
    import pytest

    from bench.speed import kernel_build
    from sagonline.render.kernels import load_arguments

    written = Path(load_arguments(tmp_path / "a", "a")["extra_include_paths"][0])
    before = Path(load_arguments(tmp_path / "b", "b")["extra_include_paths"][0])
    kernel_build.with_extension_h(before)
    changed = []
    for path in sorted(written.iterdir()):
        old, new = path.read_text().splitlines(), (before / path.name).read_text().splitlines()
        assert len(old) == len(new)
        changed += [(a, b) for a, b in zip(old, new, strict=True) if a != b]
    assert sorted(changed) == sorted(
        (line, "#include <torch/extension.h>") for line in kernel_build.LIGHT_INCLUDES.values()
    )
    with pytest.raises(ValueError, match="splat_common.h: no line"):
        kernel_build.with_extension_h(before)  # already rewritten: its includes changed

    seconds = {True: 60.0, False: 30.0}
    monkeypatch.setattr(kernel_build, "build_seconds", lambda folder, name, ext: seconds[ext])
    table = kernel_build.main(["--out", str(tmp_path / "build.csv")]).set_index("headers")
    assert table.loc[kernel_build.AS_WRITTEN, "build_s"] == 30.0
    assert table.loc[kernel_build.AS_WRITTEN, "ratio_to_before"] == 0.5
    assert table.loc[kernel_build.EXTENSION_H, "ratio_to_before"] == 1.0
    assert (tmp_path / "build.csv").is_file()
