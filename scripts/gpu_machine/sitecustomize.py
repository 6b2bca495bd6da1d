"""Python as on the GPU machines: importing a package they do not have fails.

Those machines have no package registry. What they have is listed below (ON_THE_MACHINE: what
docs/performance.md lists, and what those packages pull in), and `make gpu-bundle` carries the
pure-Python rest (CARRIED, by distribution). A step of `scripts/gpu_check.sh` that imports
anything else works where it is written and fails on its first GPU run, the one run in days.

    scripts/gpu_check.sh --quick --device cpu --as-gpu-machine

puts this folder first on PYTHONPATH. Python imports `sitecustomize` at start-up, in every
process the check starts, and from then on a top-level module that is neither in the standard
library, nor listed here, nor the project's own, is not found: importing it raises
ModuleNotFoundError, and a package's probe for an optional module sees it absent, as there.
The tests run the quick check so. `scripts/bundle_site.py` reads CARRIED to fill the bundle.
"""

from __future__ import annotations

import importlib.machinery
import os
import sys
from pathlib import Path

# Top-level modules of the machines' Python: PyTorch (with CUDA), Triton, numpy, scipy, pandas,
# opencv, scikit-image, onnx, onnxruntime, torchvision, ninja, pytest, PyYAML, pip and setuptools,
# and the packages these depend on.
# fmt: off
ON_THE_MACHINE = frozenset({
    "torch", "torchgen", "functorch", "triton", "nvidia", "torchvision", "numpy", "scipy",
    "pandas", "dateutil", "tzdata", "cv2", "skimage", "imageio", "tifffile", "lazy_loader", "PIL",
    "networkx", "onnx", "onnxruntime", "google", "flatbuffers", "ml_dtypes", "sympy", "mpmath",
    "isympy", "jinja2", "markupsafe", "filelock", "fsspec", "typing_extensions", "packaging",
    "ninja", "pytest", "_pytest", "pluggy", "iniconfig", "py", "pygments", "yaml", "_yaml", "pip",
    "setuptools", "pkg_resources", "_distutils_hack",
})
# fmt: on

# What `make gpu-bundle` carries (pure Python): distribution -> its top-level modules.
CARRIED = {
    "hydra-core": ("hydra",),
    "omegaconf": ("omegaconf",),
    "antlr4-python3-runtime": ("antlr4",),
    "plyfile": ("plyfile",),
    "rich": ("rich",),  # gsplat imports it
    "tabulate": ("tabulate",),  # pandas' to_markdown, every table the check writes
}

# gsplat is built there by the check itself, from the wheel the bundle carries
BUILT_THERE = frozenset({"gsplat"})
PROJECT = frozenset({"sagonline", "bench", "scripts", "tests", "conftest"})
ROOT = Path(__file__).resolve().parents[2]
STDLIB = Path(os.__file__).resolve().parent  # lib-dynload is inside it


def listed(name: str) -> bool:
    """Whether a top-level module `name` is one the GPU machines have, by its name."""
    carried = {module for modules in CARRIED.values() for module in modules}
    return (
        name in sys.stdlib_module_names
        or name in ON_THE_MACHINE
        or name in carried
        or name in BUILT_THERE
        or name in PROJECT
        or name.startswith("__")  # editable installs' finders, __main__
    )


def found_where_allowed(origin: str) -> bool:
    """Whether a module found at `origin` is vendored inside a listed package's folder
    (setuptools' _vendor), this checkout's (a script's sibling, the bundle) or the standard
    library's (a platform module such as _sysconfigdata_*)."""
    path = Path(origin).resolve()
    parts = path.parts
    inside = [i for i, part in enumerate(parts[:-1]) if part in ("site-packages", "dist-packages")]
    if inside:
        return listed(parts[inside[-1] + 1].removesuffix(".py"))
    return path.is_relative_to(ROOT) or path.is_relative_to(STDLIB)


class OnlyWhatTheGpuMachinesHave(importlib.machinery.PathFinder):
    """The path finder, blind to a top-level module the GPU machines do not have: importing it
    raises ModuleNotFoundError and `importlib.util.find_spec` gives None, as there (a package's
    probe for an optional module, torch's for hypothesis, sees it absent too)."""

    @classmethod
    def find_spec(cls, name, path=None, target=None):
        spec = super().find_spec(name, path, target)
        if spec is None or path is not None or "." in name or listed(name):
            return spec
        # a namespace package (setuptools' vendored jaraco) has folders, not an origin
        origins = [spec.origin] if spec.origin else list(spec.submodule_search_locations or [])
        return spec if origins and all(found_where_allowed(o) for o in origins) else None


if __name__ == "sitecustomize" and os.environ.get("SAGONLINE_AS_GPU_MACHINE") == "1":
    sys.meta_path[:] = [
        OnlyWhatTheGpuMachinesHave if finder is importlib.machinery.PathFinder else finder
        for finder in sys.meta_path
    ]
