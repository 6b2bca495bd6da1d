"""Build gsplat's CUDA extension here, for the GPU machines, so that their minutes are not spent
compiling it (58-80 s of an H200's).

    python scripts/prebuild_gsplat.py [--python python3.12] [--torch 2.11.0] [--archs 9.0]
                                      [--toolchain .gpu-toolchain] [--out .gpu-prebuilt]

(`make gsplat-prebuilt`.) The GPU machines (docs/performance.md) run Python 3.12 and PyTorch
2.11.0 with CUDA 13.0 on Hopper GPUs (compute capability 9.0). An extension is bound to the
PyTorch it was compiled against, so it is compiled in a virtual environment of its own
(--toolchain, ignored; about 5 GB) holding that Python, that PyTorch from the registry (its CUDA
libraries come with it) and the CUDA compiler of PyTorch's own CUDA version (the registry's
`cuda-toolkit` extras that PyTorch names: nvcc and its headers). No GPU is needed to compile.

gsplat's source distribution, of the version installed here, is built into a wheel holding its
CUDA extension (`gsplat/csrc.so`, for --archs) beside its CUDA sources, so that a machine the
extension does not fit still compiles them as before. The wheel and BUILT_FOR.json (the
versions it was built against) go into --out, where `make gpu-bundle` takes them
(`scripts/gsplat_bundle.py`). On this project's 2-core machine the build takes about 5 minutes.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sagonline.core.files import atomic_write_json
from sagonline.core.provenance import sha256_file

MANIFEST = "BUILT_FOR.json"


def run(*command, env: dict | None = None, capture: bool = False) -> str:
    """Run a command, its output shown (returned instead, where `capture`). A failure stops the
    build, naming the command."""
    line = " ".join(str(c) for c in command)
    print("+", line, flush=True)
    stdout = subprocess.PIPE if capture else None
    done = subprocess.run([str(c) for c in command], env=env, stdout=stdout, text=True)
    if done.returncode:
        sys.exit(f"prebuild_gsplat: `{line}` failed")
    return done.stdout or ""


def ask(interpreter: Path, code: str) -> str:
    """What `code` prints under `interpreter`, stripped."""
    return run(interpreter, "-c", code, capture=True).strip()


def toolchain(folder: Path, python: str, torch_version: str) -> Path:
    """The toolchain's interpreter: a virtual environment of `python` holding PyTorch
    `torch_version`, the CUDA compiler of its CUDA version, ninja and gsplat's build needs."""
    interpreter = folder / "bin" / "python"
    if not interpreter.exists():
        found = shutil.which(python)
        works = (
            found
            and not subprocess.run([found, "-c", "import venv"], capture_output=True).returncode
        )
        if not works:
            sys.exit(
                f"prebuild_gsplat: {python} does not run here; name the GPU machines' Python "
                "(3.12) with --python (make gsplat-prebuilt GPU_PYTHON=/path/to/python3.12)"
            )
        run(python, "-m", "venv", folder)
    install = (interpreter, "-m", "pip", "install", "--quiet")
    run(*install, f"torch=={torch_version}", "numpy", "ninja", "rich")
    requires = ask(interpreter, "import importlib.metadata as m; print(*m.requires('torch'))")
    toolkit = re.search(r"cuda-toolkit\[[^\]]*\]\s*==\s*([\d.]+)", requires)
    if toolkit is None:
        sys.exit(f"prebuild_gsplat: torch {torch_version} names no cuda-toolkit (a CPU build?)")
    run(*install, f"cuda-toolkit[nvcc,cccl,crt,nvvm]=={toolkit.group(1)}")
    return interpreter


def cuda_home(interpreter: Path) -> Path:
    """The registry's CUDA packages as a CUDA home (nvidia/cu<major>: bin/nvcc, include, lib),
    with the two names a build looks for added: lib64 and an unversioned libcudart.so."""
    found = ask(
        interpreter,
        "import torch, nvidia, os; "
        "print(os.path.join(nvidia.__path__[0], 'cu' + torch.version.cuda.split('.')[0]))",
    )
    home = Path(found)
    if not (home / "bin" / "nvcc").exists():
        sys.exit(f"prebuild_gsplat: {home} holds no bin/nvcc")
    if not (home / "lib64").exists():
        (home / "lib64").symlink_to("lib")
    runtime = sorted((home / "lib").glob("libcudart.so.*"))
    if runtime and not (home / "lib" / "libcudart.so").exists():
        (home / "lib" / "libcudart.so").symlink_to(runtime[0].name)
    return home


def build(interpreter: Path, version: str, archs: str, out: Path) -> dict:
    """gsplat `version`'s source distribution from the registry built into a wheel in `out`;
    returns what BUILT_FOR.json records."""
    home = cuda_home(interpreter)
    env = dict(
        os.environ,
        CUDA_HOME=str(home),
        PATH=f"{home / 'bin'}:{os.environ['PATH']}",
        TORCH_CUDA_ARCH_LIST=archs,
        MAX_JOBS=str(os.cpu_count() or 1),
    )
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        pip = (interpreter, "-m", "pip")
        run(
            *pip,
            "download",
            "--quiet",
            "--no-deps",
            "--no-binary",
            ":all:",
            "--no-build-isolation",
            f"gsplat=={version}",
            "-d",
            tmp,
        )
        (source,) = Path(tmp).glob("gsplat-*.tar.gz")
        run(*pip, "wheel", "--no-deps", "--no-build-isolation", source, "-w", out, env=env)
        source_sha256 = sha256_file(source)
    (wheel,) = out.glob(f"gsplat-{version}-*.whl")
    facts = ask(
        interpreter,
        "import sys, torch; v = sys.version_info; "
        "print(f'{v[0]}.{v[1]}', torch.__version__, torch.version.cuda)",
    ).split()
    compiler = run(home / "bin" / "nvcc", "--version", capture=True).strip().splitlines()[-1]
    return {
        "gsplat": version,
        "wheel": wheel.name,
        "sha256": sha256_file(wheel),
        "source_sha256": source_sha256,
        "python": facts[0],
        "torch": facts[1],
        "cuda": facts[2],
        "archs": archs,
        "compiler": compiler,
        "seconds": round(time.perf_counter() - start, 1),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--python", default="python3.12", help="the GPU machines' Python")
    parser.add_argument("--torch", default="2.11.0", help="the GPU machines' PyTorch")
    parser.add_argument("--archs", default="9.0", help="TORCH_CUDA_ARCH_LIST (Hopper: 9.0)")
    parser.add_argument("--toolchain", type=Path, default=Path(".gpu-toolchain"))
    parser.add_argument("--out", type=Path, default=Path(".gpu-prebuilt"))
    args = parser.parse_args(argv)
    version = importlib.metadata.version("gsplat")
    interpreter = toolchain(args.toolchain.resolve(), args.python, args.torch)
    partial = args.out.with_name(args.out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    built = build(interpreter, version, args.archs, partial.resolve())
    atomic_write_json(partial / MANIFEST, built)
    shutil.rmtree(args.out, ignore_errors=True)
    partial.rename(args.out)
    print(
        f"prebuild_gsplat: {args.out / built['wheel']} for Python {built['python']}, torch "
        f"{built['torch']}, compute capability {built['archs']} ({built['seconds']} s)"
    )


if __name__ == "__main__":
    main()
