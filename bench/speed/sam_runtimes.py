"""The SAM-family models' halves on each runtime (`bench.speed.sam --parts runtimes,decoders`):
the image encoder on onnxruntime and on PyTorch at each precision, the prompt decoder on
onnxruntime and on PyTorch; per row the time, the largest difference from onnxruntime's outputs
and the box IoU on the captures' photographs. `python -m bench.speed.sam_runtimes CSV [DEVICE]`
prints the fastest encoder precision of such a table whose IoU holds (`fastest_precision`)."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from bench.speed.render import no_warmup, timed
from bench.speed.sam import CAPTURES, DATA, photos, segmenter
from sagonline.core.provenance import sha256_file
from sagonline.segment.mask_geometry import box_of, iou


def captured(
    count: int, data: Path | None, captures: tuple[str, ...] = CAPTURES
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, RGB image, truth) of the first `count` photographs of each of `captures` that
    is in `data`."""
    root = data or DATA
    return [p for c in captures if (root / c).is_dir() for p in photos(c, count, root)]


def iou_column(photos: int) -> str:
    return f"box IoU ({photos} photo{'s' * (photos != 1)})"


def runtime_table(
    models: list[str],
    device: str,
    repeats: int,
    count: int,
    data: Path | None = None,
    options: dict | None = None,
    precisions: tuple[str, ...] | None = None,
    captures: tuple[str, ...] = CAPTURES,
) -> pd.DataFrame:
    """The encoder under each runtime on `device`: onnxruntime (on the CPU unless it has a CUDA
    provider) and PyTorch (`encoder_runtime=torch`) at each of `precisions` (default: fp32, fp16
    and bf16 on CUDA, fp32 on the CPU, where fp16 is slow). Per image: the encoder's time
    (median of `repeats`, the frame already on the host), the largest difference from
    onnxruntime's outputs, and the box IoU on the photographs (the decoder on onnxruntime's CPU
    in every row). `options`: segmenter settings (say another `encoder` file) for every model."""
    from sagonline.segment.sam_sessions import open_pair

    shots = captured(count, data, captures)
    if precisions is None:
        precisions = ("fp32", "fp16", "bf16") if device.startswith("cuda") else ("fp32",)
    runs = [("onnxruntime", "fp32"), *(("torch", p) for p in precisions)]
    rows = []
    for kind in models:
        base = segmenter(kind, **(options or {}))
        reference = None
        for runtime, precision in runs:
            pair = open_pair(
                base.encoder,
                base.decoder,
                threads=2,
                device=device,
                cache=None,
                runtime=runtime,
                precision=precision,
                make_target="make weights",
            )
            name = pair.encoder.get_inputs()[0].name
            frame = pair.preprocess(shots[0][1])
            outputs = pair.encoder.run(None, {name: frame})  # also the warm-up of those timed
            reference = reference or outputs
            # both runtimes hand numpy back, so a timed call includes the GPU's work
            run = partial(pair.encoder.run, None, {name: frame})
            seconds = timed(run, repeats, "cpu", no_warmup)
            ious = []
            for i, (name_of, im, gt) in enumerate(shots):
                # the first photograph's embedding from the outputs just compared, not encoded again
                emb = (
                    pair.embedding_of(pair.kept(outputs, name_of), im.shape[:2])
                    if i == 0
                    else pair.embed(im)
                )
                answers = pair.decode(emb, None, None, box_of(gt))
                ious.append(iou(max(answers, key=lambda a: a.predicted_iou).mask, gt))
            rows.append(
                {
                    "model": kind,
                    "encoder": f"{base.encoder.name} (sha256 {pair.encoder_sha256[:12]})",
                    "encoder runtime": runtime,
                    "precision": precision,
                    "device": device if runtime.startswith("torch") or pair.note == "" else "cpu",
                    "encoder ms/image": round(1000 * seconds, 1),
                    "operators per call": getattr(pair.encoder, "operators_per_call", None),
                    "max |difference| from onnxruntime": float(
                        max(np.abs(o - r).max() for o, r in zip(outputs, reference, strict=True))
                    ),
                    iou_column(len(shots)): round(float(np.mean(ious)), 4),
                }
            )
    return pd.DataFrame(rows)


def decoder_table(
    models: list[str],
    device: str,
    repeats: int,
    count: int,
    data: Path | None = None,
    options: dict | None = None,
    captures: tuple[str, ...] = CAPTURES,
) -> pd.DataFrame:
    """The prompt decoder on onnxruntime (on the CPU unless it has a CUDA provider) and on
    PyTorch on `device` (`decoder_runtime=torch`; and again with its shape arithmetic run on
    every call, which shows what reusing it saves), the embeddings made once on onnxruntime: ms
    per prompt (median of 5 x `repeats`, a box and a box with the previous logits in turn),
    the largest logit difference from onnxruntime's, and the box IoU on the photographs."""
    from sagonline.segment.sam_sessions import open_pair

    shots = captured(count, data, captures)
    rows = []
    for kind in models:
        base = segmenter(kind, **(options or {}))
        runs = {"onnxruntime": "onnxruntime", "torch": "torch"}
        runs["torch (shape arithmetic every call)"] = "torch"
        if device.startswith("cuda"):  # each prompt shape's call replayed as one launch
            runs["torch (CUDA graphs)"] = "torch"
        pairs = {
            name: open_pair(
                base.encoder,
                base.decoder,
                threads=2,
                device=device,
                cache=None,
                decoder_runtime=runtime,
                cuda_graphs=name == "torch (CUDA graphs)",
                make_target="make weights",
            )
            for name, runtime in runs.items()
        }
        pairs["torch (shape arithmetic every call)"].decoder.reuse_shapes = False
        reference = pairs["onnxruntime"]
        decoder_named = f"{base.decoder.name} (sha256 {sha256_file(base.decoder)[:12]})"
        encoder_named = f"{base.encoder.name} (sha256 {reference.encoder_sha256[:12]})"
        embeddings = [(reference.embed(im), box_of(gt), gt) for _, im, gt in shots]
        first = [reference.decode(e, None, None, b)[0].logits for e, b, _ in embeddings]
        for runtime, pair in pairs.items():
            emb, box, _ = embeddings[0]
            prompts = [(None, None, box, None), (None, None, box, first[0])]
            calls = iter(prompts * (5 * repeats + 1))
            seconds = timed(
                lambda p=pair, e=emb, c=calls: p.decode(e, *next(c)), 5 * repeats, "cpu"
            )
            gaps, ious = [], []
            for (e, b, gt), logits in zip(embeddings, first, strict=True):
                for prompt in ((None, None, b, None), (None, None, b, logits)):
                    want = reference.decode(e, *prompt)
                    got = pair.decode(e, *prompt)
                    gaps += [
                        float(np.abs(g.logits - w.logits).max())
                        for g, w in zip(got, want, strict=True)
                    ]
                answers = pair.decode(e, None, None, b)
                ious.append(iou(max(answers, key=lambda a: a.predicted_iou).mask, gt))
            rows.append(
                {
                    "model": kind,
                    "decoder": decoder_named,
                    "embeddings from": encoder_named,
                    "decoder runtime": runtime,
                    "device": device if runtime.startswith("torch") or pair.note == "" else "cpu",
                    "decoder ms/prompt": round(1000 * seconds, 1),
                    "operators per call": getattr(pair.decoder, "operators_per_call", None),
                    "max |logit difference| from onnxruntime": max(gaps),
                    iou_column(len(shots)): round(float(np.mean(ious)), 4),
                }
            )
    return pd.DataFrame(rows)


def fastest_precision(table: pd.DataFrame, device: str = "cuda", points: float = 0.5) -> str:
    """The precision of the fastest PyTorch encoder on `device` in a `runtime_table` whose box
    IoU lies within `points` (percentage points) of fp32's there; fp32 where none is faster.
    ValueError where the table has no fp32 row for `device`."""
    rows = table[(table["encoder runtime"] == "torch") & (table["device"] == device)]
    column = next(c for c in table.columns if c.startswith("box IoU"))
    fp32 = rows[rows["precision"] == "fp32"]
    if fp32.empty:
        raise ValueError(f"no PyTorch fp32 encoder row on {device} to hold the others to")
    held = rows[100 * (fp32[column].iloc[0] - rows[column]).abs() <= points]
    return str(held.sort_values("encoder ms/image")["precision"].iloc[0])


if __name__ == "__main__":  # the fastest precision of a runtimes CSV (scripts/gpu_check.sh)
    import sys

    print(fastest_precision(pd.read_csv(sys.argv[1]), *sys.argv[2:3]))
