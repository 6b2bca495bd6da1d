"""Put what a GPU fit of a capture needs from this machine's CPU fit into the GPU bundle.

    python scripts/bundle_cpu_fit.py duck_queen --bundle .gpu-bundle

From the capture's default fit of seed 0 (`make scenes`, `bench.runners.fit_captures`):
- its triangulated start points (init_points.store) into <bundle>/data/<capture>/gaussians/,
  where a fit of another recipe of the same seed reads them: the GPU fit then starts from the
  CPU fit's points (a GPU machine without a package registry may have no pycolmap to
  triangulate with);
- its fit_config.json and fit_metrics.json into <bundle>/cpu_fit/<capture>/, the CPU row that
  `bench.tables.gpu_fit --cpu-fit` sets beside the GPU fit.

Without such a fit it says so and exits 0: the bundle is still usable (the GPU fit then starts
from random points, and its table has no CPU row).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from sagonline.datasets.fits import gaussians_dir

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def bundle_cpu_fit(capture: str, bundle: Path, data: Path = SHARED_DATA) -> Path | None:
    """Copy the capture's seed-0 CPU fit's start points and figures into `bundle`; returns the
    fit folder they came from, or None when there is no finished fit with start points."""
    fit = gaussians_dir(data / capture, capture)
    needed = [fit / name for name in ("init_points.store", "fit_config.json", "fit_metrics.json")]
    if not all(p.is_file() for p in needed):
        return None
    points, config, metrics = needed
    (bundle / "data" / capture / "gaussians").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(points, bundle / "data" / capture / "gaussians" / points.name)
    (bundle / "cpu_fit" / capture).mkdir(parents=True, exist_ok=True)
    for path in (config, metrics):
        shutil.copyfile(path, bundle / "cpu_fit" / capture / path.name)
    return fit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", help="a capture of ../shared/data with a default fit of seed 0")
    ap.add_argument("--bundle", type=Path, default=Path(".gpu-bundle"))
    ap.add_argument("--data", type=Path, default=SHARED_DATA, help="where the capture lies")
    args = ap.parse_args()
    fit = bundle_cpu_fit(args.capture, args.bundle, args.data)
    if fit is None:
        print(
            f"gpu-bundle: no CPU fit of {args.capture} (seed 0) with start points here: the GPU "
            "fit will triangulate (where pycolmap is) or start from random points, and its "
            "table has no CPU row (`python -m bench.runners.fit_captures --captures "
            f"{args.capture} --seeds 0` fits it)"
        )
    else:
        print(f"gpu-bundle: {args.capture}'s CPU fit (seed 0): start points and figures from {fit}")


if __name__ == "__main__":
    main()
