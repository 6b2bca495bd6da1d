"""gsplat for the GPU machines: packed into the bundle here, unpacked and made ready there.

    python scripts/gsplat_bundle.py pack --bundle .gpu-bundle [--prebuilt .gpu-prebuilt]
    python scripts/gsplat_bundle.py install --bundle .gpu-bundle --site .gsplat-build/site
    python scripts/gsplat_bundle.py ready --site .gsplat-build/site     # on CUDA

`pack` (`make gpu-bundle`) writes gsplat-<version>.tar.xz, the installed package (a wheel's
files, xz-compressed: gsplat 1.5.3's sources 3.8 MB where the registry's wheel is 6.5 MB; 5.4 MB
with the compiled extension), and gsplat-<version>.json (where it came from; what its compiled
extension was built against, or null). The wheel is the one `make gsplat-prebuilt` compiled
(`scripts/prebuild_gsplat.py`) where that is of the version installed here, else the
registry's, whose CUDA sources compile on first use.

`install` (`scripts/gpu_check.sh`, the step "gsplat install") unpacks it into --site. A compiled
extension built for another Python or PyTorch than this one is set aside there, saying why.

`ready` (the step "gsplat build") imports gsplat's extension in a fresh process and rasterises
one Gaussian on CUDA. Where the compiled extension fails that (another GPU, another driver),
it is set aside and gsplat compiles its CUDA sources instead (MAX_JOBS on all cores), and the
rasterisation is tried again. The step says which extension works.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import lzma
import os
import subprocess
import sys
import tarfile
import tempfile
import time
import zipfile
from pathlib import Path

from sagonline.core.files import atomic_write, atomic_write_json
from sagonline.core.provenance import sha256_file

MANIFEST = "BUILT_FOR.json"  # scripts/prebuild_gsplat.py writes it beside its wheel
SET_ASIDE = ".not-used"  # appended to a compiled extension's name where it is not used


def prebuilt_wheel(prebuilt: Path, version: str) -> tuple[Path, dict] | None:
    """The compiled wheel in `prebuilt` and its BUILT_FOR.json, where it is gsplat `version`'s
    and its sha256 holds; None (saying why) otherwise."""
    manifest = prebuilt / MANIFEST
    if not manifest.exists():
        return None
    built = json.loads(manifest.read_text())
    wheel = prebuilt / built["wheel"]
    if built["gsplat"] != version:
        print(f"gsplat_bundle: {prebuilt} holds gsplat {built['gsplat']}, not {version}: unused")
        return None
    if not wheel.exists() or sha256_file(wheel) != built["sha256"]:
        sys.exit(f"gsplat_bundle: {wheel} is missing or not the file {manifest} names")
    return wheel, built


def registry_wheel(version: str, folder: Path) -> Path:
    """gsplat `version`'s wheel from the registry (its CUDA sources, no compiled extension)."""
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--quiet",
            "--no-deps",
            "--only-binary",
            ":all:",
            f"gsplat=={version}",
            "-d",
            str(folder),
        ],
        check=True,
    )
    return next(folder.glob(f"gsplat-{version}-*.whl"))


def pack(bundle: Path, wheel: Path, built: dict | None, version: str) -> Path:
    """Write gsplat `version`'s `wheel` into `bundle` as the installed files (tar.xz) and where
    they came from (json: `built` is BUILT_FOR.json or None), each atomically; returns the
    tar.xz. Earlier versions' files there are removed once these are written."""
    packed, record = bundle / f"gsplat-{version}.tar.xz", bundle / f"gsplat-{version}.json"
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp)
        with zipfile.ZipFile(wheel) as archive:
            archive.extractall(tree)
        files = [p for p in sorted(tree.rglob("*")) if p.is_file() and "__pycache__" not in p.parts]

        def write(path: Path) -> None:
            with tarfile.open(path, "w:xz", preset=9) as tar:
                for file in files:
                    tar.add(file, arcname=str(file.relative_to(tree)))

        atomic_write(packed, write)
    source = {"gsplat": version, "from": wheel.name, "sha256": sha256_file(wheel)}
    atomic_write_json(record, source | {"built_for": built})
    for old in [*bundle.glob("gsplat-*.tar.xz"), *bundle.glob("gsplat-*.json")]:
        if old not in (packed, record):
            old.unlink()
    return packed


def this_machine() -> dict:
    """This Python's and PyTorch's versions, as BUILT_FOR.json names them."""
    import torch

    major, minor = sys.version_info[:2]
    return {"python": f"{major}.{minor}", "torch": torch.__version__, "cuda": torch.version.cuda}


def set_aside(site: Path, why: str) -> list[Path]:
    """Rename gsplat's compiled extension in `site` so that gsplat compiles its sources instead;
    returns the files renamed."""
    moved = []
    for extension in sorted((site / "gsplat").glob("csrc*.so")):
        target = extension.with_name(extension.name + SET_ASIDE)
        extension.replace(target)
        moved.append(target)
        print(f"gsplat_bundle: {extension.name} set aside ({why}); gsplat compiles its sources")
    return moved


def mismatch(built: dict, here: dict) -> str | None:
    """Why an extension built for `built` cannot load under `here`; None where it can."""
    wrong = [f"{key} {built[key]} (here {here[key]})" for key in here if built[key] != here[key]]
    return "built for " + ", ".join(wrong) if wrong else None


def install(bundle: Path, site: Path, here: dict | None = None) -> str:
    """Unpack the bundle's gsplat into `site`, setting aside a compiled extension built for
    another Python or PyTorch than `here` (default: this one); returns a line saying what."""
    packed = sorted(bundle.glob("gsplat-*.tar.xz"))
    if len(packed) != 1:
        sys.exit(f"gsplat_bundle: {bundle} holds {len(packed)} gsplat-*.tar.xz, not one")
    source = packed[0].with_suffix("").with_suffix(".json")
    if not source.exists():
        sys.exit(f"gsplat_bundle: {source} is missing beside {packed[0].name} (make gpu-bundle)")
    record = json.loads(source.read_text())
    site.mkdir(parents=True, exist_ok=True)
    try:
        with tarfile.open(packed[0]) as tar:
            tar.extractall(site, filter="data")
    except (tarfile.TarError, EOFError, lzma.LZMAError) as exc:
        sys.exit(f"gsplat_bundle: {packed[0]} cannot be unpacked ({exc}): make gpu-bundle again")
    built = record["built_for"]
    if built is None:
        return f"gsplat {record['gsplat']} installed ({record['from']}: compiles on first use)"
    why = mismatch(built, here or this_machine())
    if why is not None:
        set_aside(site, why)
        return f"gsplat {record['gsplat']} installed; its compiled extension unused ({why})"
    return (
        f"gsplat {record['gsplat']} installed with its compiled extension (Python "
        f"{built['python']}, torch {built['torch']}, compute capability {built['archs']})"
    )


def smoke() -> None:
    """Load gsplat's extension and rasterise one Gaussian on CUDA; say which extension it is.
    Exits non-zero where either fails."""
    start = time.perf_counter()
    import torch

    if not torch.cuda.is_available():
        sys.exit("gsplat: no CUDA device here to rasterise on")
    import gsplat

    if any(Path(gsplat.__file__).parent.glob("csrc*.so")):
        try:
            importlib.import_module("gsplat.csrc")
        except ImportError as why:  # gsplat then compiles its sources, below
            print(f"gsplat: its compiled extension does not load here ({why})")
    from gsplat.cuda._backend import _C

    if _C is None:
        sys.exit("gsplat: its CUDA extension neither loaded nor compiled (no CUDA toolkit?)")
    loaded = time.perf_counter() - start
    cuda = torch.device("cuda")
    _, alpha, _ = gsplat.rasterization(
        means=torch.tensor([[0.0, 0.0, 3.0]], device=cuda),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=cuda),
        scales=torch.full((1, 3), 0.5, device=cuda),
        opacities=torch.ones(1, device=cuda),
        colors=torch.ones(1, 3, device=cuda),
        viewmats=torch.eye(4, device=cuda)[None],
        Ks=torch.tensor([[[16.0, 0.0, 8.0], [0.0, 16.0, 8.0], [0.0, 0.0, 1.0]]], device=cuda),
        width=16,
        height=16,
    )
    centre = float(alpha[0, 8, 8, 0])
    if not centre > 0.5:
        sys.exit(f"gsplat: one Gaussian rasterised to alpha {centre} at its centre, not > 0.5")
    kind = "compiled here" if _C.__name__.startswith("gsplat_cuda") else "prebuilt"
    gpu = torch.cuda.get_device_name()
    print(f"gsplat: {kind} extension {_C.__file__} (with PyTorch) loaded in {loaded:.1f} s")
    print(f"gsplat: one Gaussian rasterised on {gpu}, alpha {centre:.3f} at its centre")


def attempt(site: Path) -> tuple[bool, str]:
    """`smoke` in a fresh process (a broken extension can crash it): whether it passed, and
    its output."""
    path = os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, __file__, "smoke"],
        env=dict(os.environ, PYTHONPATH=path),
        capture_output=True,
        text=True,
    )
    return done.returncode == 0, (done.stdout + done.stderr).strip()


def ready(site: Path, try_it=attempt) -> bool:
    """gsplat works on CUDA: with its compiled extension, or else with the one compiled from
    its sources once the compiled one is set aside."""
    passed, said = try_it(site)
    print(said)
    if passed:
        return True
    tail = said.splitlines()[-1] if said else "no output"
    if not set_aside(site, f"it failed: {tail}"):
        return False
    passed, said = try_it(site)
    print(said)
    return passed


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("pack", "install", "ready", "smoke"))
    parser.add_argument("--bundle", type=Path, default=Path(".gpu-bundle"))
    parser.add_argument("--prebuilt", type=Path, default=Path(".gpu-prebuilt"))
    parser.add_argument("--site", type=Path, default=Path(".gsplat-build/site"))
    args = parser.parse_args(argv)
    if args.action == "pack":
        version = importlib.metadata.version("gsplat")
        with tempfile.TemporaryDirectory() as tmp:
            wheel, built = prebuilt_wheel(args.prebuilt, version) or (
                registry_wheel(version, Path(tmp)),
                None,
            )
            packed = pack(args.bundle, wheel, built, version)
        kind = (
            "its CUDA sources alone: they compile there, 98 s on an H200; `make gsplat-prebuilt` "
            "compiles them here"
            if built is None
            else f"compiled for torch {built['torch']}"
        )
        print(f"gsplat_bundle: {packed} ({packed.stat().st_size / 1e6:.1f} MB; {kind})")
    elif args.action == "install":
        print(install(args.bundle, args.site))
    elif args.action == "ready":
        import torch

        if not torch.cuda.is_available():  # not the extension's failure: nothing set aside
            sys.exit("gsplat_bundle ready: no CUDA device here")
        sys.exit(0 if ready(args.site) else "gsplat: not usable on CUDA (above)")
    else:
        smoke()


if __name__ == "__main__":
    main()
