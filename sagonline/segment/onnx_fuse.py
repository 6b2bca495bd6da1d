"""Spelled-out subgraphs of an ONNX graph replaced by one PyTorch call each, before
`segment.onnx_torch` runs it: on a GPU each node is a kernel launch from Python, and a call of
the SAM-family encoders and decoders is bound by those launches, not by their arithmetic.

Five patterns, as PyTorch's exporter writes them (the values between a pattern's nodes read by
no other node and no graph output, its constants checked by value):
- **LayerNorm**: ReduceMean, Sub, Pow 2, ReduceMean, Add eps, Sqrt, Div, Mul by a weight, Add a
  weight (9 nodes) -> `LayerNormalization` over the last axis, or `ChannelLayerNorm` over axis 1
  (SAM's LayerNorm2d, its weights shaped [C, 1, 1]);
- **GELU**: Div by sqrt(2), Erf, Add 1, Mul by the input, Mul 0.5 (5 nodes) -> `Gelu`;
- **a linear layer**: MatMul by a 2-D weight, Add a 1-D weight (2 nodes) -> `Linear` (its
  weight stored transposed, as `F.linear` reads it);
- **a Gemm by a stored weight** (1 node) -> the same `Linear`, its weight not transposed on
  every call;
- **attention**: MatMul of q and k transposed, a constant scale (Mul or Div) and a constant
  bias (Add) if any, Softmax over the last axis, MatMul by v (3-5 nodes) -> `Attention`
  (PyTorch's `scaled_dot_product_attention`).

`LayerNormalization` and `Gelu` are ONNX's own operators (opsets 17 and 20); `ChannelLayerNorm`,
`Linear` and `Attention` are this project's, made only here, and run by the functions in
`FUSED_OPS`. A fused call computes the same function; its values differ from the spelled-out
one's by float rounding.
"""

from __future__ import annotations

import math
import os
from collections import Counter, defaultdict

import torch
import torch.nn.functional as F

from sagonline.segment.onnx_device import accumulated_in_float32, as_type, together
from sagonline.segment.onnx_graph import Node

__all__ = ["FUSED_OPS", "fuse_patterns", "fusing_by_default"]


def fusing_by_default() -> bool:
    """Whether a session fuses unless told (SAGONLINE_ONNX_FUSE: `1`, the default, or `0`:
    every graph runs as written, say to tell a fused call's failure on a new machine from the
    graph's own)."""
    value = os.environ.get("SAGONLINE_ONNX_FUSE") or "1"
    if value not in ("0", "1"):
        raise ValueError(f"SAGONLINE_ONNX_FUSE={value!r}: use 1 (fuse, the default) or 0")
    return value == "1"


# --- the fused calls (`LayerNormalization` is among `onnx_ops.OPS` already) ----------------------


def _run_channel_layer_norm(node, x, scale, bias):
    """SAM's LayerNorm2d: x [N, C, ...] normalised over C at each place, scale and bias [C]
    (the graph's [C, 1, ...] flattened when fused). An input of another rank than the one the
    weights' shape was written for gets the written graph's values: normalised over axis 1,
    the weights broadcast in their own shape."""
    eps = float(node.attrs["epsilon"])
    if x.dim() != node.attrs["rank"]:
        centred = x - x.mean(dim=1, keepdim=True)
        spread = torch.sqrt((centred * centred).mean(dim=1, keepdim=True) + eps)
        shape = (-1,) + (1,) * (node.attrs["rank"] - 2)
        return centred / spread * scale.reshape(shape) + bias.reshape(shape)
    moved = F.layer_norm(
        x.movedim(1, -1), x.shape[1:2], as_type(scale, x.dtype), as_type(bias, x.dtype), eps=eps
    )
    return moved.movedim(-1, 1)


def _run_linear(node, x, w, b):
    """MatMul by a weight, then Add b [M]: x [..., K], w [M, K] (the
    graph's [K, M], transposed when fused)."""
    x, w, b = together(x, w, b)
    return F.linear(x, w, b)


def _run_attention(node, q, kt, v, bias=None):
    """softmax(q @ kt * scale + bias) @ v: q [..., L, E], kt [..., E, S],
    v [..., S, Ev], bias broadcast to [..., L, S] or None."""
    q, kt, v, bias = together(q, kt, v, bias)
    mask = None if bias is None else as_type(bias, q.dtype)
    scale = float(node.attrs["scale"])
    return F.scaled_dot_product_attention(q, kt.transpose(-1, -2), v, attn_mask=mask, scale=scale)


FUSED_OPS = {  # op -> its function, as `onnx_ops.OPS` holds them
    "Gelu": lambda node, x: F.gelu(x, approximate=node.attrs.get("approximate", "none")),
    "ChannelLayerNorm": _run_channel_layer_norm,
    "Linear": accumulated_in_float32(_run_linear),
    "Attention": accumulated_in_float32(_run_attention),
}

# --- the patterns ---------------------------------------------------------------------------------


class _Graph:
    """The nodes with who reads each value, and the graph's constants (name -> tensor)."""

    def __init__(
        self, nodes: list[Node], constants: dict[str, torch.Tensor], keep: set[str], opset: int
    ):
        self.nodes, self.constants, self.keep, self.opset = nodes, constants, keep, opset
        self.readers: dict[str, list[int]] = defaultdict(list)
        self.made_by: dict[str, Node] = {}
        for i, node in enumerate(nodes):
            for name in node.inputs:
                if name:
                    self.readers[name].append(i)
            self.made_by.update((name, node) for name in node.outputs)

    def only_reader(self, name: str, op: str) -> tuple[int, Node] | None:
        """The one node reading `name`, if it is an `op` and `name` is not a graph output."""
        readers = self.readers.get(name, [])
        if name in self.keep or len(readers) != 1 or self.nodes[readers[0]].op != op:
            return None
        return readers[0], self.nodes[readers[0]]

    def derived(self, name: str, how: str, fn) -> str:
        """The name of a new constant fn(constant `name`), made once (the graph's own is left
        for any other node reading it)."""
        new = f"{name}:{how}"
        if new not in self.constants:
            self.constants[new] = fn(self.constants[name])
        return new

    def constant(self, name: str) -> torch.Tensor | None:  # [...] or None
        return self.constants.get(name)

    def scalar(self, name: str) -> float | None:
        """A one-valued constant's value (None for anything else)."""
        c = self.constants.get(name)
        return float(c.reshape(-1)[0]) if c is not None and c.numel() == 1 else None

    def other(self, node: Node, name: str) -> str | None:
        """A binary node's input other than `name` (None if `name` is not one of its two)."""
        if len(node.inputs) != 2 or name not in node.inputs:
            return None
        a, b = node.inputs
        return b if a == name else a


def _reduced_axes(node: Node, graph: _Graph) -> list[int] | None:
    """A keepdims ReduceMean's axes, from its attribute or its constant second input."""
    if node.op != "ReduceMean" or not node.attrs.get("keepdims", 1):
        return None
    if "axes" in node.attrs:
        return [int(a) for a in node.attrs["axes"]]
    axes = graph.constant(node.inputs[1]) if len(node.inputs) > 1 else None
    return None if axes is None else [int(a) for a in axes.reshape(-1).tolist()]


def _chain(graph: _Graph, name: str, *ops: str) -> list[tuple[int, Node]] | None:
    """The nodes after `name`, each the only reader of the one before it, with these ops."""
    found = []
    for op in ops:
        step = graph.only_reader(name, op)
        if step is None:
            return None
        found.append(step)
        name = step[1].outputs[0]
    return found


def _layer_norm(graph: _Graph, i: int, mean: Node) -> tuple[list[int], Node] | None:
    axes = _reduced_axes(mean, graph)
    if axes not in ([-1], [1]):
        return None
    x = mean.inputs[0]
    sub = graph.only_reader(mean.outputs[0], "Sub")
    if sub is None or sub[1].inputs != [x, mean.outputs[0]]:
        return None
    centred = sub[1].outputs[0]
    readers = sorted(graph.readers.get(centred, []))
    if centred in graph.keep or len(readers) != 2:
        return None
    power, divide = (graph.nodes[r] for r in readers)
    if power.op != "Pow" or power.inputs[0] != centred or graph.scalar(power.inputs[1]) != 2.0:
        return None
    rest = _chain(graph, power.outputs[0], "ReduceMean", "Add", "Sqrt", "Div", "Mul", "Add")
    if rest is None or _reduced_axes(rest[0][1], graph) != axes:
        return None
    (_, var), (_, add_eps), (_, sqrt), (_, div), (_, scale), (_, shift) = rest
    eps = graph.scalar(graph.other(add_eps, var.outputs[0]) or "")
    if eps is None or div is not divide or div.inputs != [centred, sqrt.outputs[0]]:
        return None
    gamma = graph.other(scale, div.outputs[0])
    beta = graph.other(shift, scale.outputs[0])
    weights = [graph.constant(gamma or ""), graph.constant(beta or "")]
    if any(w is None for w in weights) or weights[0].shape != weights[1].shape:
        return None
    shape = list(weights[0].shape)
    if axes == [-1] and len(shape) == 1:
        op, attrs = "LayerNormalization", {"axis": -1, "epsilon": eps}
    elif axes == [1] and len(shape) >= 1 and all(d == 1 for d in shape[1:]):
        op, attrs = "ChannelLayerNorm", {"epsilon": eps, "rank": len(shape) + 1}
        gamma, beta = (graph.derived(n, "flat", lambda t: t.reshape(-1)) for n in (gamma, beta))
    else:
        return None
    used = [i, sub[0], readers[0], *(j for j, _ in rest)]
    return used, Node(op, [x, gamma, beta], [shift.outputs[0]], attrs)


def _gelu(graph: _Graph, i: int, div: Node) -> tuple[list[int], Node] | None:
    x = div.inputs[0]
    root2 = graph.scalar(div.inputs[1]) if len(div.inputs) == 2 else None
    if root2 is None or not math.isclose(root2, math.sqrt(2.0), rel_tol=1e-6):
        return None
    rest = _chain(graph, div.outputs[0], "Erf", "Add", "Mul", "Mul")
    if rest is None:
        return None
    (_, erf), (_, add_one), (_, times_x), (_, half) = rest
    if graph.scalar(graph.other(add_one, erf.outputs[0]) or "") != 1.0:
        return None
    if graph.other(times_x, add_one.outputs[0]) != x:
        return None
    if graph.scalar(graph.other(half, times_x.outputs[0]) or "") != 0.5:
        return None
    return [i, *(j for j, _ in rest)], Node("Gelu", [x], [half.outputs[0]], {})


def _linear(graph: _Graph, i: int, matmul: Node) -> tuple[list[int], Node] | None:
    x, w = matmul.inputs
    weight = graph.constant(w)
    if weight is None or weight.dim() != 2 or x in graph.constants:
        return None
    add = graph.only_reader(matmul.outputs[0], "Add")
    if add is None:
        return None
    b = graph.other(add[1], matmul.outputs[0])
    bias = graph.constant(b or "")
    if bias is None or list(bias.shape) != [weight.shape[1]]:
        return None
    w = graph.derived(w, "T", lambda t: t.T.contiguous())
    return [i, add[0]], Node("Linear", [x, w, b], [add[1].outputs[0]], {})


def _rank(graph: _Graph, name: str) -> int | None:
    """A value's rank where a Transpose made it (its permutation's length), else None."""
    made = graph.made_by.get(name)
    return len(made.attrs["perm"]) if made is not None and "perm" in made.attrs else None


def _attention(graph: _Graph, i: int, scores: Node) -> tuple[list[int], Node] | None:
    """MatMul(q, kt), scaled by a constant (Mul or Div) or not, a constant bias added or not,
    Softmax over the last axis, MatMul by v -> Attention(q, kt, v, bias)."""
    q, kt = scores.inputs
    if q in graph.constants or kt in graph.constants:
        return None
    used, name, scale, bias = [i], scores.outputs[0], 1.0, ""
    step = graph.only_reader(name, "Mul") or graph.only_reader(name, "Div")
    if step is not None:
        c = graph.scalar(step[1].inputs[1])
        if c is None or step[1].inputs[0] != name or c == 0.0:
            return None
        scale = c if step[1].op == "Mul" else 1.0 / c
        used.append(step[0])
        name = step[1].outputs[0]
    step = graph.only_reader(name, "Add")
    if step is not None:
        bias = graph.other(step[1], name) or ""
        if bias not in graph.constants:
            return None
        used.append(step[0])
        name = step[1].outputs[0]
    softmax = graph.only_reader(name, "Softmax")
    if softmax is None:
        return None
    axis = softmax[1].attrs.get("axis", -1 if graph.opset >= 13 else 1)
    rank = _rank(graph, kt) or _rank(graph, q)
    if axis != -1 and (rank is None or axis != rank - 1):
        return None
    mix = graph.only_reader(softmax[1].outputs[0], "MatMul")
    if mix is None or mix[1].inputs[0] != softmax[1].outputs[0]:
        return None
    used += [softmax[0], mix[0]]
    v = mix[1].inputs[1]
    return used, Node("Attention", [q, kt, v, bias], [mix[1].outputs[0]], {"scale": scale})


def _matmul(graph: _Graph, i: int, node: Node) -> tuple[list[int], Node] | None:
    """A MatMul begins a linear layer or an attention."""
    return _linear(graph, i, node) or _attention(graph, i, node)


def _gemm(graph: _Graph, i: int, gemm: Node) -> tuple[list[int], Node] | None:
    """A Gemm by a stored weight, unscaled, its bias 1-D: the same `Linear` (its weight stored
    as `F.linear` reads it, not transposed on every call)."""
    a, w, *bias = gemm.inputs
    weight, attrs = graph.constant(w), gemm.attrs
    if weight is None or a in graph.constants or not bias or attrs.get("transA", 0):
        return None
    if float(attrs.get("alpha", 1.0)) != 1.0 or float(attrs.get("beta", 1.0)) != 1.0:
        return None
    b = graph.constant(bias[0])
    if b is None or list(b.shape) != [weight.shape[0 if attrs.get("transB", 0) else 1]]:
        return None
    if not attrs.get("transB", 0):
        w = graph.derived(w, "T", lambda t: t.T.contiguous())
    return [i], Node("Linear", [a, w, bias[0]], gemm.outputs, {})


PATTERNS = {"ReduceMean": _layer_norm, "Div": _gelu, "MatMul": _matmul, "Gemm": _gemm}


def fuse_patterns(
    nodes: list[Node],  # in an order where each node follows those it reads
    constants: dict[str, torch.Tensor],  # name -> [...] the weights and folded constants; added
    # to: a linear layer's weight transposed, a LayerNorm2d's flattened
    keep: set[str],  # the graph's outputs, which no pattern may swallow
    opset: int,  # the graph's (Softmax's default axis depends on it)
) -> tuple[list[Node], Counter]:
    """The nodes with each pattern replaced by its one call, placed where its last node was
    (so still in order), and how many of each fused op were made."""
    graph = _Graph(nodes, constants, keep, opset)
    replaced: dict[int, Node | None] = {}  # node index -> its replacement (None: dropped)
    made: Counter = Counter()
    for i, node in enumerate(nodes):
        match = i not in replaced and PATTERNS.get(node.op, lambda *_: None)(graph, i, node)
        if not match or any(j in replaced for j in match[0]):
            continue
        used, fused = match
        for j in used:
            replaced[j] = None
        replaced[max(used)] = fused
        made[fused.op] += 1
    out = [replaced.get(i, node) for i, node in enumerate(nodes)]
    return [n for n in out if n is not None], made
