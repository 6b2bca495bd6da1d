"""Seconds to compile the CPU kernels (sagonline/render/csrc), as written and with the header
they included before: torch/extension.h, PyTorch's whole C++ frontend, in every source file.

    python -m bench.speed.kernel_build [--rounds 1] [--out reports/bench_kernel_build.csv]

Each build is a fresh one, in a folder of its own under a temporary folder, through the
project's own build arguments (`sagonline.render.kernels.load_arguments`: the same flags, the
same sources), compiled by ninja (MAX_JOBS, else its default: about one compiler per core).
The two take turns, `--rounds` times each, the earlier header first. A row's figure is the
median of its rounds. The environment's own build (`kernel_root`) is left alone.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import pandas as pd

from bench import OUT_HELP, print_and_write
from sagonline.core.machine import describe_device
from sagonline.render.kernels import load_arguments, project_ninja

AS_WRITTEN = "as written (torch/types.h; pybind's casters for the bindings)"
EXTENSION_H = "torch/extension.h in every source (before)"
# the lines that include less than torch/extension.h, by the source file holding each
LIGHT_INCLUDES = {
    "splat_common.h": "#include <torch/types.h>",
    "raster_cpu.cpp": "#include <torch/csrc/utils/pybind.h>",
}


def with_extension_h(sources: Path) -> None:
    """Rewrite the copied sources in `sources` to include torch/extension.h where they now
    include its parts (raises if a line is missing: the kernels' includes changed)."""
    for name, line in LIGHT_INCLUDES.items():
        path = sources / name
        text = path.read_text()
        if line not in text:
            raise ValueError(f"{path}: no line {line!r} to replace")
        path.write_text(text.replace(line, "#include <torch/extension.h>"))


def build_seconds(folder: Path, name: str, extension_h: bool) -> float:
    """Compile the kernels from scratch in `folder`; the seconds it took."""
    from torch.utils import cpp_extension

    arguments = load_arguments(folder, name)
    if extension_h:
        with_extension_h(Path(arguments["extra_include_paths"][0]))
    with project_ninja():  # the ninja every build of the kernels runs
        start = time.perf_counter()
        cpp_extension.load(**arguments)
        return time.perf_counter() - start


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(prog="python -m bench.speed.kernel_build", description=__doc__)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--out", default=None, help=OUT_HELP)
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    variants = {EXTENSION_H: True, AS_WRITTEN: False}
    times: dict[str, list[float]] = {name: [] for name in variants}
    with tempfile.TemporaryDirectory(prefix="kernel-build-") as root:
        for round_ in range(args.rounds):
            for i, (variant, extension_h) in enumerate(variants.items()):
                name = f"kernel_build_{round_}_{i}"
                seconds = build_seconds(Path(root) / name, name, extension_h)
                times[variant].append(seconds)
                print(f"round {round_ + 1}: {variant}: {seconds:.1f} s", flush=True)
    before = statistics.median(times[EXTENSION_H])
    machine = describe_device()
    table = pd.DataFrame(
        {
            "headers": name,
            "build_s": round(statistics.median(t), 1),
            "ratio_to_before": round(statistics.median(t) / before, 3),
            "rounds": len(t),
            "compile_jobs": os.environ.get("MAX_JOBS", "ninja's default"),
            "device": machine["cpu"],
            "load_average_1m": machine["load_average_1m"],
        }
        for name, t in times.items()
    )
    print_and_write(table, args.out)
    return table


if __name__ == "__main__":
    main()
