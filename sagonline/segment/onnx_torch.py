"""An ONNX graph run by PyTorch: the SAM-family image encoders on CUDA where onnxruntime has
no CUDA provider (`segmenter.encoder_runtime`), and on the CPU for their check.

The graph is read from an `.onnx` or an `.ort` file (`segment.onnx_graph`). Its nodes run in
dependency order on torch tensors; only the operators these encoders use are implemented, and
any other is refused by name when the file is opened. Integer tensors
(shapes, indices) stay on the CPU, so shape arithmetic never waits on the GPU.

`TorchSession` answers the three calls `sam_onnx.SamPair` makes of an onnxruntime session
(`get_inputs`, `get_outputs`, `run`), so either runtime serves a pair.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sagonline.segment.onnx_graph import TORCH_TYPES, Node, ValueInfo, read_graph, topological

__all__ = ["PRECISIONS", "TorchSession", "encoder_runtime"]

PRECISIONS = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}

# --- the operators --------------------------------------------------------------------------------


def _ints(t) -> list[int]:
    return [int(v) for v in (t.tolist() if isinstance(t, torch.Tensor) else t)]


def _axes(node: Node, args: list, index: int) -> list[int] | None:
    """An operator's axes: the attribute (before opset 13/18) or the input at `index`."""
    if "axes" in node.attrs:
        return _ints(node.attrs["axes"])
    if len(args) > index and args[index] is not None:
        return _ints(args[index])
    return None


def _same_device(a: torch.Tensor, b: torch.Tensor):
    if a.device != b.device:  # a CPU shape constant meets a tensor on the GPU
        if a.device.type == "cpu":
            a = a.to(b.device)
        else:
            b = b.to(a.device)
    return a, b


def _binary(fn):
    def op(node, x, y):
        x, y = _same_device(x, y)
        return fn(x, y)

    return op


def _div(x, y):
    if not x.is_floating_point() and not y.is_floating_point():
        return torch.div(x, y, rounding_mode="trunc")
    return x / y


def _reshape(node, x, shape):
    dims = _ints(shape)
    if not node.attrs.get("allowzero", 0):
        dims = [x.shape[i] if d == 0 else d for i, d in enumerate(dims)]
    return x.reshape(dims)


def _slice(node, x, starts, ends, axes=None, steps=None):
    starts, ends = _ints(starts), _ints(ends)
    axes = _ints(axes) if axes is not None else list(range(len(starts)))
    steps = _ints(steps) if steps is not None else [1] * len(starts)
    for s, e, a, st in zip(starts, ends, axes, steps, strict=True):
        a, size = a % x.dim(), x.shape[a % x.dim()]
        if st > 0:  # Python's slice clamps as ONNX does
            x = x[(slice(None),) * a + (slice(s, e, st),)]
            continue
        # torch has no negative steps: the indices, clamped as ONNX clamps them
        s = min(max(s + size if s < 0 else s, 0), size - 1)
        e = min(max(e + size if e < 0 else e, -1), size - 1)
        x = x.index_select(a, torch.arange(s, e, st, device=x.device))
    return x


def _split(node, x, split=None):
    axis = node.attrs.get("axis", 0)
    sizes = node.attrs.get("split")
    if sizes is None and split is not None:
        sizes = _ints(split)
    if sizes is None:
        parts = len(node.outputs)
        size = x.shape[axis]
        sizes = [math.ceil(size / parts)] * (parts - 1)
        sizes.append(size - sum(sizes))
    return list(torch.split(x, list(sizes), dim=axis))


def _softmax(node, x, opset):
    axis = node.attrs.get("axis", -1 if opset >= 13 else 1)
    axis = axis % x.dim()
    if opset >= 13 or axis == x.dim() - 1:
        return torch.softmax(x, dim=axis)
    lead = x.shape[:axis]  # before opset 13: softmax over everything from `axis` on
    return torch.softmax(x.reshape(math.prod(lead), -1), dim=1).reshape(x.shape)


def _pad_pairs(pads: list[int]) -> list[int]:
    """ONNX's [b0, b1, ..., e0, e1, ...] as F.pad's (last dim first) pairs."""
    n = len(pads) // 2
    out = []
    for d in reversed(range(n)):
        out += [pads[d], pads[d + n]]
    return out


def _pad(node, x, pads=None, value=None, axes=None):
    pads = _ints(pads) if pads is not None else _ints(node.attrs["pads"])
    mode = node.attrs.get("mode", "constant")
    if axes is not None:
        full = [0] * (2 * x.dim())
        ax = [a % x.dim() for a in _ints(axes)]
        for i, a in enumerate(ax):
            full[a], full[a + x.dim()] = pads[i], pads[i + len(ax)]
        pads = full
    fill = float(value.reshape(-1)[0]) if value is not None and value.numel() else 0.0
    if mode == "constant":
        return F.pad(x, _pad_pairs(pads), value=fill)
    spatial = pads[2 : x.dim()] + pads[x.dim() + 2 :]  # torch pads only beyond batch, channel
    return F.pad(x, _pad_pairs(spatial), mode={"reflect": "reflect", "edge": "replicate"}[mode])


def _conv(node, x, w, b=None):
    k = w.dim() - 2
    pads = _ints(node.attrs.get("pads", [0] * 2 * k))
    if node.attrs.get("auto_pad", "NOTSET") not in ("NOTSET", "VALID"):
        raise ValueError(f"Conv auto_pad={node.attrs['auto_pad']} is not supported")
    if pads[:k] != pads[k:]:
        x, pads = F.pad(x, _pad_pairs([0, 0, *pads[:k], 0, 0, *pads[k:]])), [0] * 2 * k
    conv = {1: F.conv1d, 2: F.conv2d, 3: F.conv3d}[k]
    return conv(
        x,
        w,
        b,
        stride=_ints(node.attrs.get("strides", [1] * k)),
        padding=pads[:k],
        dilation=_ints(node.attrs.get("dilations", [1] * k)),
        groups=int(node.attrs.get("group", 1)),
    )


def _max_pool(node, x):
    k = _ints(node.attrs["kernel_shape"])
    pads = _ints(node.attrs.get("pads", [0] * 2 * len(k)))
    if pads[: len(k)] != pads[len(k) :]:
        raise ValueError("MaxPool with uneven pads is not supported")
    return F.max_pool2d(
        x,
        k,
        stride=_ints(node.attrs.get("strides", k)),
        padding=pads[: len(k)],
        dilation=_ints(node.attrs.get("dilations", [1] * len(k))),
        ceil_mode=bool(node.attrs.get("ceil_mode", 0)),
    )


def _resize(node, x, roi=None, scales=None, sizes=None):
    mode = node.attrs.get("mode", "nearest")
    transform = node.attrs.get("coordinate_transformation_mode", "half_pixel")
    if sizes is not None and sizes.numel():
        size = _ints(sizes)[2:]
    else:
        factors = scales.tolist()[2:]
        size = [int(math.floor(d * f)) for d, f in zip(x.shape[2:], factors, strict=True)]
    if mode == "nearest":
        nearest = node.attrs.get("nearest_mode", "round_prefer_floor")
        if transform == "asymmetric" and nearest == "floor":
            return F.interpolate(x, size=size, mode="nearest")
        raise ValueError(f"Resize nearest with {transform}/{nearest} is not supported")
    if mode == "linear":
        modes = {1: "linear", 2: "bilinear", 3: "trilinear"}
        if transform in ("half_pixel", "pytorch_half_pixel"):
            return F.interpolate(x, size=size, mode=modes[len(size)], align_corners=False)
        if transform == "align_corners":
            return F.interpolate(x, size=size, mode=modes[len(size)], align_corners=True)
    cubic = mode == "cubic" and node.attrs.get("cubic_coeff_a", -0.75) == -0.75
    if cubic and transform in ("half_pixel", "pytorch_half_pixel"):
        return F.interpolate(x, size=size, mode="bicubic", align_corners=False)
    raise ValueError(f"Resize mode={mode} with {transform} is not supported")


def _gather(node, x, index):
    axis = node.attrs.get("axis", 0) % x.dim()
    index = index.to(x.device).long()
    index = torch.where(index < 0, index + x.shape[axis], index)
    out = x.index_select(axis, index.reshape(-1))
    return out.reshape((*x.shape[:axis], *index.shape, *x.shape[axis + 1 :]))


def _layer_norm(node, x, scale, bias=None):
    axis = node.attrs.get("axis", -1) % x.dim()
    return F.layer_norm(
        x,
        x.shape[axis:],
        scale.to(x.dtype),
        None if bias is None else bias.to(x.dtype),
        eps=float(node.attrs.get("epsilon", 1e-5)),
    )


def _reduce_mean(node, x, axes=None):
    dims = _axes(node, [x, axes], 1)
    keep = bool(node.attrs.get("keepdims", 1))
    if dims is None:
        return x.mean(dim=tuple(range(x.dim())), keepdim=keep)
    return x.mean(dim=tuple(dims), keepdim=keep)


def _unsqueeze(node, x, axes=None):
    dims = sorted(a % (x.dim() + len(_axes(node, [x, axes], 1))) for a in _axes(node, [x, axes], 1))
    for a in dims:
        x = x.unsqueeze(a)
    return x


def _squeeze(node, x, axes=None):
    dims = _axes(node, [x, axes], 1)
    if dims is None:
        return x.squeeze()
    for a in sorted((d % x.dim() for d in dims), reverse=True):
        x = x.squeeze(a)
    return x


def _constant_of_shape(node, shape):
    value = node.attrs.get("value")
    fill = torch.from_numpy(np.array(value)).reshape(-1) if value is not None else torch.zeros(1)
    return torch.full(_ints(shape), fill[0].item(), dtype=fill.dtype)


def _shape(node, x):
    dims = list(x.shape)[node.attrs.get("start", 0) : node.attrs.get("end", None)]
    return torch.tensor(dims, dtype=torch.int64)


def _transpose(node, x):
    perm = node.attrs.get("perm")
    return x.permute(*_ints(perm)) if perm is not None else x.permute(*reversed(range(x.dim())))


OPS = {
    "Add": _binary(torch.add),
    "Sub": _binary(torch.sub),
    "Mul": _binary(torch.mul),
    "Div": _binary(_div),
    "Pow": _binary(torch.pow),
    "MatMul": _binary(torch.matmul),
    "Erf": lambda node, x: torch.erf(x),
    "Sqrt": lambda node, x: torch.sqrt(x),
    "Constant": lambda node: torch.from_numpy(np.asarray(node.attrs["value"]).copy()),
    "Reshape": _reshape,
    "Transpose": _transpose,
    "Concat": lambda node, *xs: torch.cat([x.to(xs[0].device) for x in xs], dim=node.attrs["axis"]),
    "Shape": _shape,
    "Gather": _gather,
    "ReduceMean": _reduce_mean,
    "Slice": _slice,
    "Conv": _conv,
    "ConstantOfShape": _constant_of_shape,
    "Cast": lambda node, x: x.to(TORCH_TYPES[node.attrs["to"]]),
    "Pad": _pad,
    "Split": _split,
    "Squeeze": _squeeze,
    "Unsqueeze": _unsqueeze,
    "LayerNormalization": _layer_norm,
    "MaxPool": _max_pool,
    "Resize": _resize,
}


def _run(node: Node, args: list, opset: int) -> list[torch.Tensor]:
    """The node's outputs for its inputs (None for an optional one left out)."""
    while args and args[-1] is None:  # optional inputs left out at the end
        args.pop()
    out = _softmax(node, args[0], opset) if node.op == "Softmax" else OPS[node.op](node, *args)
    return out if isinstance(out, list) else [out]


# --- running a graph ------------------------------------------------------------------------------


class TorchSession:
    """An ONNX graph on `device` at `precision` (fp32, fp16 or bf16: floating tensors and the
    weights in that type, outputs back in float32), with onnxruntime's session calls."""

    def __init__(self, path: Path, device: str = "cpu", precision: str = "fp32"):
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: use one of {', '.join(PRECISIONS)}")
        self.graph = read_graph(Path(path))
        missing = sorted({n.op for n in self.graph.nodes} - {*OPS, "Softmax"})
        if missing:
            raise ValueError(f"{path}: operators {', '.join(missing)} have no PyTorch path here")
        known = set(self.graph.initializers) | {v.name for v in self.graph.inputs}
        self.device, self.dtype = torch.device(device), PRECISIONS[precision]
        inits = self.graph.initializers
        stored = {k: torch.from_numpy(np.array(v)) for k, v in inits.items()}
        # a node of weights alone (an int8 weight's Cast and scale, scripts/compact_weights.py)
        # runs once, here, in float32 before the session's type, as onnxruntime folds it
        nodes = []
        for node in topological(self.graph.nodes, known):
            if node.inputs and all(n in stored for n in node.inputs if n):
                args = [stored[n] if n else None for n in node.inputs]
                stored.update(zip(node.outputs, _run(node, args, self.graph.opset), strict=True))
            else:
                nodes.append(node)
        read = {n for node in nodes for n in node.inputs} | {o.name for o in self.graph.outputs}
        self.nodes = nodes
        self.weights = {k: self._place(v) for k, v in stored.items() if k in read}
        # after each node, the values no later node reads (an encoder's activations at 1024 px
        # are gigabytes if all are kept)
        kept = set(self.weights) | {o.name for o in self.graph.outputs}
        last = {name: i for i, n in enumerate(self.nodes) for name in n.inputs if name}
        self.free_after: list[list[str]] = [[] for _ in self.nodes]
        for name, i in last.items():
            if name not in kept:
                self.free_after[i].append(name)

    def _place(self, t: torch.Tensor) -> torch.Tensor:
        """Floating tensors to the device in the session's type; integers stay on the CPU."""
        if t.is_floating_point():
            return t.to(self.device, self.dtype)
        return t

    def get_inputs(self) -> list[ValueInfo]:
        return self.graph.inputs

    def get_outputs(self) -> list[ValueInfo]:
        return self.graph.outputs

    @torch.inference_mode()
    def forward(
        self,
        feeds: dict[str, torch.Tensor],  # input name -> its tensor, say [1, 3, 1024, 1024]
    ) -> list[torch.Tensor]:  # the outputs in the graph's order, say [1, 256, 64, 64]
        """The graph's outputs for `feeds` (input name -> tensor), in the graph's order."""
        values: dict[str, torch.Tensor | None] = {"": None, **self.weights}
        values.update({k: self._place(v) for k, v in feeds.items()})
        opset = self.graph.opset
        for i, node in enumerate(self.nodes):
            outs = _run(node, [values[name] for name in node.inputs], opset)
            if node.op in ("Constant", "ConstantOfShape", "Cast"):
                outs = [self._place(o) if o.is_floating_point() else o for o in outs]
            for name, value in zip(node.outputs, outs, strict=True):
                values[name] = value
            for name in self.free_after[i]:
                values.pop(name, None)
        return [values[o.name] for o in self.graph.outputs]

    def run(self, output_names, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """onnxruntime's `InferenceSession.run`: numpy in, float32 numpy out."""
        outs = self.forward({k: torch.from_numpy(np.asarray(v)) for k, v in feeds.items()})
        names = [o.name for o in self.graph.outputs]
        chosen = names if output_names is None else list(output_names)
        by_name = dict(zip(names, outs, strict=True))
        return [by_name[n].float().cpu().numpy() for n in chosen]


def encoder_runtime(runtime: str, device: str) -> str:
    """What runs a SAM-family encoder for `segmenter.encoder_runtime` on `device`: auto takes
    onnxruntime unless the device is CUDA, onnxruntime has no CUDA provider and PyTorch has
    CUDA (then torch)."""
    if runtime != "auto":
        return runtime
    if not device.startswith("cuda"):
        return "onnxruntime"
    import onnxruntime as ort

    if "CUDAExecutionProvider" in ort.get_available_providers() or not torch.cuda.is_available():
        return "onnxruntime"
    return "torch"
