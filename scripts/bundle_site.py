"""Copy the pure-Python packages the GPU machines lack into the GPU bundle's site folder.

    python scripts/bundle_site.py .gpu-bundle/site

The packages are scripts/gpu_machine/sitecustomize.py's CARRIED (the list the quick check run
`--as-gpu-machine` allows), copied with their metadata from this environment, where the project
is installed. `scripts/gpu_check.sh` puts the folder on PYTHONPATH.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import shutil
from pathlib import Path

LISTING = Path(__file__).resolve().parent / "gpu_machine" / "sitecustomize.py"


def carried() -> dict[str, tuple[str, ...]]:
    """CARRIED of the GPU machine's listing: distribution -> its top-level modules."""
    spec = importlib.util.spec_from_file_location("gpu_machine_listing", LISTING)
    assert spec is not None and spec.loader is not None
    listing = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(listing)
    return listing.CARRIED


def bundle_site(site: Path) -> list[str]:
    """Copy each carried distribution's installed files (modules and dist-info) into `site`;
    returns the distributions with their versions. A distribution that is not installed here
    is refused by name."""
    site.mkdir(parents=True, exist_ok=True)
    copied = []
    for name in carried():
        try:
            dist = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError as missing:
            message = f"bundle_site: {name} is not installed here (`make install` first)"
            raise SystemExit(message) from missing
        for file in dist.files or []:
            source = Path(str(dist.locate_file(file))).resolve()
            parts = Path(file).parts
            if parts[0] == ".." or "__pycache__" in parts or not source.is_file():
                continue  # scripts installed outside site-packages, bytecode
            target = site / file
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)
        copied.append(f"{name} {dist.version}")
    return copied


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("site", type=Path, help="the bundle's site folder (.gpu-bundle/site)")
    args = parser.parse_args(argv)
    print("bundled:", ", ".join(bundle_site(args.site)))


if __name__ == "__main__":
    main()
