"""The compiled kernels: a truncated library is built again, not loaded."""

from __future__ import annotations


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
