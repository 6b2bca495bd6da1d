"""A model file small enough to travel to a GPU machine: its large weights as int8.

    python scripts/compact_weights.py weights/sam2_tiny/encoder.ort /tmp/encoder.w8.onnx

What reaches a GPU machine is capped (64 MiB with the checkout), and SAM 2 Hiera-tiny's encoder
is 135 MB of float32 (`scripts/bundle_models.py` packs each real model's encoder and decoder
so for `make gpu-bundle`). This writes the same graph as a standard `.onnx` file in which every
float weight of at least `--min-elements` values is stored as int8 with one float32 scale per
output channel (symmetric), widened by a `Cast` and a `Mul` by its scales:
- a MatMul's weight [K, N]: a scale per column (axis 1);
- a Conv's weight [O, I, kh, kw]: a scale per filter (axis 0);
- any other (an added positional embedding [1, C, H, W]): a scale per channel (axis 1).
Small tensors (biases, norms) and integers stay as they are. Only the weights' storage changes:
both runtimes fold a node of weights alone when they open the file (onnxruntime's constant
folding; `segment.onnx_torch` likewise), so the encoder computes at fp32, fp16 or bf16 exactly
as with the original file, on weights rounded to 255 levels a channel. (ONNX's own
`DequantizeLinear` is not used: onnxruntime fuses it with the MatMul after it into an int8
product that quantises the activations too, a different computation.)

It then runs both files on onnxruntime (CPU) on one frame and prints each output's largest
difference and the cosine similarity of the two, so the rounding's cost is on record (an
encoder's; a decoder's prompts are no random frame).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sagonline.core.files import atomic_write
from sagonline.segment.onnx_graph import OnnxGraph, read_graph, topological

ONNX_FLOAT = 1  # onnx.TensorProto.FLOAT (onnx is imported where a file is written)


def along(ndim: int, axis: int | None) -> list[int]:
    """The shape that broadcasts one value per index of `axis` over `ndim` dimensions."""
    shape = [1] * ndim
    if axis is not None:
        shape[axis] = -1
    return shape


def weight_axis(consumers: list[tuple[str, int]], ndim: int) -> int | None:
    """The axis that gets one scale for a weight read by `consumers` ((op, input index) pairs),
    None for a weight left per tensor (a single scale)."""
    if consumers and all(op == "MatMul" and index == 1 for op, index in consumers) and ndim == 2:
        return 1
    if consumers and all(op == "Conv" and index == 1 for op, index in consumers):
        return 0
    return 1 if ndim >= 2 else None


def quantise(weight: np.ndarray, axis: int | None) -> tuple[np.ndarray, np.ndarray]:
    """`weight` as int8 values and float32 scales (one per index of `axis`, or one in all):
    value ~= int8 * scale, rounded to the nearest of 255 levels in [-max|w|, max|w|]."""
    w = np.asarray(weight, np.float32)
    if axis is None:
        peak = np.abs(w).max(keepdims=True).reshape(())
    else:
        others = tuple(d for d in range(w.ndim) if d != axis)
        peak = np.abs(w).max(axis=others)
    scale = np.where(peak > 0, peak / 127.0, 1.0).astype(np.float32)
    values = np.clip(np.rint(w / scale.reshape(along(w.ndim, axis))), -127, 127).astype(np.int8)
    return values, scale


def to_onnx(graph: OnnxGraph, min_elements: int):
    """The graph as an `onnx.ModelProto` with its large float weights stored as int8."""
    from onnx import helper, numpy_helper

    consumers: dict[str, list[tuple[str, int]]] = {}
    for node in graph.nodes:
        for index, name in enumerate(node.inputs):
            consumers.setdefault(name, []).append((node.op, index))
    initializers, widen = [], []
    for name, value in graph.initializers.items():
        value = np.asarray(value)
        if value.dtype != np.float32 or value.size < min_elements:
            initializers.append(numpy_helper.from_array(np.array(value, order="C"), name))
            continue
        axis = weight_axis(consumers.get(name, []), value.ndim)
        values, scale = quantise(value, axis)
        initializers += [
            numpy_helper.from_array(values, f"{name}.int8"),
            numpy_helper.from_array(scale.reshape(along(value.ndim, axis)), f"{name}.scale"),
        ]
        widen += [
            helper.make_node("Cast", [f"{name}.int8"], [f"{name}.float"], to=ONNX_FLOAT),
            helper.make_node("Mul", [f"{name}.float", f"{name}.scale"], [name]),
        ]

    def attribute(value):
        if isinstance(value, np.ndarray):
            return numpy_helper.from_array(np.array(value, order="C"))
        return value

    known = set(graph.initializers) | {i.name for i in graph.inputs}
    nodes = widen + [
        helper.make_node(n.op, n.inputs, n.outputs, **{k: attribute(v) for k, v in n.attrs.items()})
        for n in topological(graph.nodes, known)  # an .ort file keeps its own order
    ]

    def value_info(info):
        return helper.make_tensor_value_info(info.name, ONNX_FLOAT, info.shape or None)

    body = helper.make_graph(
        nodes,
        "compact",
        [value_info(i) for i in graph.inputs],
        [value_info(o) for o in graph.outputs],
        initializers,
    )
    model = helper.make_model(body, opset_imports=[helper.make_opsetid("", graph.opset)])
    model.ir_version = min(model.ir_version, 8)  # what onnxruntime 1.16 and later read
    return model


def compare(original: Path, compact: Path, seed: int = 0) -> list[tuple[str, float, float]]:
    """(output, largest |difference|, cosine similarity) of the two files on onnxruntime's CPU
    for one random frame of the encoder's input shape; none for a model of several inputs (a
    decoder's prompts are no random frame: `tests/segment/test_compact_weights.py` compares
    the real decoders' masks)."""
    import onnxruntime as ort

    sessions = [
        ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
        for p in (original, compact)
    ]
    if len(sessions[0].get_inputs()) != 1:
        return []
    first = sessions[0].get_inputs()[0]
    shape = [d if isinstance(d, int) else 1 for d in first.shape]
    frame = np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
    a, b = (s.run(None, {first.name: frame}) for s in sessions)
    names = [o.name for o in sessions[0].get_outputs()]
    rows = []
    for name, x, y in zip(names, a, b, strict=True):
        x, y = x.ravel().astype(np.float64), y.ravel().astype(np.float64)
        cosine = float(x @ y / max(np.linalg.norm(x) * np.linalg.norm(y), 1e-30))
        rows.append((name, float(np.abs(x - y).max()), cosine))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", type=Path, help="an .onnx or .ort encoder")
    ap.add_argument("out", type=Path, help="the compact .onnx file to write")
    ap.add_argument("--min-elements", type=int, default=4096, help="smaller weights stay float")
    ap.add_argument("--no-compare", action="store_true", help="skip running both on a frame")
    args = ap.parse_args()
    if not args.source.is_file():
        raise SystemExit(f"compact_weights: {args.source}: not found (make weights)")
    try:
        graph = read_graph(args.source)
    except ValueError as exc:
        raise SystemExit(f"compact_weights: {exc}") from None
    model = to_onnx(graph, args.min_elements)
    blob = model.SerializeToString()
    atomic_write(args.out, lambda p: p.write_bytes(blob))
    print(
        f"{args.out}: {args.out.stat().st_size / 1e6:.1f} MB "
        f"(from {args.source.stat().st_size / 1e6:.1f} MB)"
    )
    if not args.no_compare:
        rows = compare(args.source, args.out)
        if not rows:
            print("  not compared: the model takes several inputs (a decoder's prompts)")
        for name, largest, cosine in rows:
            print(f"  {name}: largest |difference| {largest:.4g}, cosine {cosine:.6f}")


if __name__ == "__main__":
    main()
