"""Peak memory of reading a large scene file, against the file's size.

    python -m bench.speed.read [--gigabytes 2] [--dir /tmp] [--out reports/bench_read.csv] [--quick]

Writes a 3DGS `point_cloud.ply` of the full 62-property layout (SH degree 3, normals) of about
`--gigabytes` GB, streamed row block by row block so that writing it needs little memory, then
reads it with `sagonline.scene.io.read_scene` in a fresh process and reports that process's peak
resident memory (ru_maxrss) less its resident memory before the read (torch and numpy loaded),
as a multiple of the file's size. The file is removed afterwards. --quick: a 10 MB file.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from bench import OUT_HELP, REPORTS, ROOT
from sagonline.core.files import atomic_write_text

PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
PROPS += [f"f_rest_{i}" for i in range(45)]
PROPS += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]

READER = """
import resource, sys, time
import torch  # noqa: F401
from sagonline.scene.io import read_scene
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
g = read_scene(sys.argv[1])
took = time.perf_counter() - start
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(len(g), before * 1024, peak * 1024, took)
"""


def write_big_ply(path: Path, rows: int, block: int = 1 << 18) -> None:
    """A valid random 3DGS scene of `rows` Gaussians, written block by block."""
    rng = np.random.default_rng(0)
    dtype = np.dtype([(p, "<f4") for p in PROPS])
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {rows}\n" + "".join(f"property float {p}\n" for p in PROPS)
    with open(path, "wb") as f:
        f.write((header + "end_header\n").encode())
        for start in range(0, rows, block):
            n = min(block, rows - start)
            data = np.zeros(n, dtype)
            for p in ("x", "y", "z"):
                data[p] = rng.uniform(-5, 5, n)
            for p in ("scale_0", "scale_1", "scale_2"):
                data[p] = rng.uniform(-6, -2, n)
            data["rot_0"] = 1.0
            data["opacity"] = rng.normal(size=n)
            data.tofile(f)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gigabytes", type=float, default=2.0)
    parser.add_argument("--dir", default="/tmp")
    parser.add_argument("--out", default=str(REPORTS / "bench_read.csv"), help=OUT_HELP)
    parser.add_argument("--quick", action="store_true", help="a 10 MB file")
    args = parser.parse_args()
    if args.quick:
        args.gigabytes = 0.01
    rows = int(args.gigabytes * 1e9 / (4 * len(PROPS)))
    path = Path(args.dir) / f"bench_read_{rows}.ply"
    try:
        start = time.perf_counter()
        write_big_ply(path, rows)
        took = time.perf_counter() - start
        print(f"wrote {path} ({path.stat().st_size / 1e9:.2f} GB) in {took:.0f} s")
        out = subprocess.run(
            [sys.executable, "-c", READER, str(path)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()
    finally:
        path.unlink(missing_ok=True)
    n, before, peak, took = int(out[0]), int(out[1]), int(out[2]), float(out[3])
    size = rows * 4 * len(PROPS)
    table = pd.DataFrame(
        [
            {
                "gaussians": n,
                "file_gb": round(size / 1e9, 3),
                "read_s": round(took, 1),
                "peak_gb": round((peak - before) / 1e9, 3),
                "peak_over_file": round((peak - before) / size, 3),
            }
        ]
    )
    print(table.to_markdown(index=False))
    atomic_write_text(args.out, table.to_csv(index=False))


if __name__ == "__main__":
    main()
