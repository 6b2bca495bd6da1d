"""An ONNX graph run by PyTorch: the SAM-family image encoders on CUDA where onnxruntime has
no CUDA provider (`segmenter.encoder_runtime`), their prompt decoders there on request
(`segmenter.decoder_runtime`), and both on the CPU for their check.

The graph is read from an `.onnx` or an `.ort` file (`segment.onnx_graph`). Its nodes run in
dependency order on torch tensors (`segment.onnx_ops`); only the operators these models use are
implemented, and any other is refused by name when the file is opened. Integer tensors
(shapes, indices) stay on the CPU, so shape arithmetic never waits on the GPU; nodes of weights
and constants alone run once, when the file is opened, and shape arithmetic once per input
shape (`TorchSession._shape_bound`). On CUDA, `cuda_graphs` replays the rest of each input
shape's call as one CUDA graph (`segmenter.cuda_graphs`).

`TorchSession` answers the three calls `sam_onnx.SamPair` makes of an onnxruntime session
(`get_inputs`, `get_outputs`, `run`), so either runtime serves a pair.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sagonline.segment.onnx_device import device_copies, to_device
from sagonline.segment.onnx_fuse import FUSED_OPS, fuse_patterns, fusing_by_default
from sagonline.segment.onnx_graph import Node, ValueInfo, read_graph, topological
from sagonline.segment.onnx_ops import HOST_READ, OPS, softmax

__all__ = ["PRECISIONS", "TorchSession", "encoder_runtime", "to_host"]

PRECISIONS = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}


def _run_node(node: Node, args: list, opset: int) -> list[torch.Tensor]:
    """The node's outputs for its inputs (None for an optional one left out)."""
    while args and args[-1] is None:  # optional inputs left out at the end
        args.pop()
    out = softmax(node, args[0], opset) if node.op == "Softmax" else OPS[node.op](node, *args)
    return out if isinstance(out, list) else [out]


# What decides an operator's output shape (`TorchSession._shape_bound`): its inputs' shapes
# alone, or its first input's shape and its other inputs' values.
SHAPE_FROM_SHAPES = {
    *("Add", "Sub", "Mul", "Div", "Pow", "Equal", "Where", "Erf", "Sqrt", "Neg", "Relu"),
    *("Sigmoid", "Sin", "Cos", "Floor", "Reciprocal", "Not", "Cast", "Softmax", "MatMul"),
    *("Gemm", "Conv", "ConvTranspose", "MaxPool", "LayerNormalization", "Transpose"),
    *("Concat", "Gather", "ScatterND", "ArgMax", "Flatten", "Shape", "Clip"),
    *FUSED_OPS,
}
SHAPE_FROM_VALUES = {
    *("Reshape", "Expand", "Tile", "Slice", "Resize", "Pad", "Split", "Squeeze", "Unsqueeze"),
    *("ReduceMean", "ReduceMax", "OneHot"),
}


# --- running a graph ------------------------------------------------------------------------------


@dataclass
class Replay:
    """One key's CUDA graph: copy new inputs into `inputs`, `launch()`, read `outputs`."""

    launch: Callable[[], None]  # the graph's replay
    inputs: dict[str, torch.Tensor]
    outputs: list[torch.Tensor]
    keep: tuple  # what its kernels read by address: the key's bound values, the device copies


def record_cuda_graph(
    run: Callable[[], list[torch.Tensor]],  # () -> the outputs, [...] each
):
    """run()'s kernels captured as one CUDA graph, after a warm-up run on a side stream (as a
    capture wants): (its replay, the outputs each replay rewrites)."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        run()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    # thread_local: what other threads do meanwhile (the student training) is not the capture's
    with torch.cuda.graph(graph, capture_error_mode="thread_local"):
        outputs = run()
    return graph.replay, outputs


def first_error(exc: BaseException) -> str:
    """The first line of the error that began `exc`'s chain, with the node it rose in (the note
    `TorchSession._run` adds): a capture's end raises its own ("operation failed due to a
    previous error during capture") over the one inside it."""
    chain = [exc]
    while (nxt := chain[-1].__cause__ or chain[-1].__context__) and len(chain) < 8:
        chain.append(nxt)

    def said(e: BaseException) -> str:
        line = str(e).splitlines()[0] if str(e) else type(e).__name__
        return "; ".join([*getattr(e, "__notes__", []), line])

    first = chain[-1]
    return said(first) if first is exc else f"{said(first)}; then: {said(exc)}"


# Input keys (shapes) a session captures at most; past them a new key runs eagerly
MAX_GRAPHS = 16


class TorchSession:
    """An ONNX graph on `device` at `precision` (fp32, fp16 or bf16: floating tensors and the
    weights in that type, outputs back in float32), with onnxruntime's session calls.

    cuda_graphs: each key's kernels (`_key`: a prompt's shapes) are captured as one CUDA graph on
    its first call and replayed from then on, one launch instead of hundreds. A capture that
    fails, or whose replay differs from the eager run, is said once and that key runs eagerly.

    fuse: the graph's spelled-out LayerNorms, GELUs, linear layers and attentions run as one
    call each (`segment.onnx_fuse`); False runs every node as written (what fusing saves);
    None: as SAGONLINE_ONNX_FUSE says (fused unless it is 0)."""

    reuse_shapes = True  # False: shape arithmetic on every call (what reusing it saves)
    record = staticmethod(record_cuda_graph)  # how a key's graph is captured

    def __init__(
        self,
        path: Path,
        device: str = "cpu",
        precision: str = "fp32",
        cuda_graphs: bool = False,
        fuse: bool | None = None,
    ):
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: use one of {', '.join(PRECISIONS)}")
        if cuda_graphs and torch.device(device).type != "cuda":
            raise ValueError(f"CUDA graphs need a CUDA device, not {device!r}")
        self.cuda_graphs = cuda_graphs
        self.replays: dict[tuple, Replay | None] = {}  # None: refused, runs eagerly
        self.path = Path(path)
        self.graph = read_graph(self.path)
        missing = sorted({n.op for n in self.graph.nodes} - {*OPS, "Softmax"})
        if missing:
            raise ValueError(f"{path}: operators {', '.join(missing)} have no PyTorch path here")
        known = set(self.graph.initializers) | {v.name for v in self.graph.inputs}
        self.device, self.dtype = torch.device(device), PRECISIONS[precision]
        inits = self.graph.initializers
        stored = {k: torch.from_numpy(np.array(v)) for k, v in inits.items()}
        # a node of weights and constants alone (an int8 weight's Cast and scale,
        # scripts/compact_weights.py) runs once, here, in float32 before the session's type, as
        # onnxruntime folds it
        nodes = []
        for node in topological(self.graph.nodes, known):
            if all(n in stored for n in node.inputs if n):  # a Constant too
                args = [stored[n] if n else None for n in node.inputs]
                outs = _run_node(node, args, self.graph.opset)
                stored.update(zip(node.outputs, outs, strict=True))
            else:
                nodes.append(node)
        self.fused = Counter()  # fused op -> how many `segment.onnx_fuse` made
        if fusing_by_default() if fuse is None else fuse:
            outputs = {o.name for o in self.graph.outputs}
            nodes, self.fused = fuse_patterns(nodes, stored, outputs, self.graph.opset)
        read = {n for node in nodes for n in node.inputs} | {o.name for o in self.graph.outputs}
        self.nodes = nodes
        # a weight only ever read on the host (a Resize's scales, a Clip's bounds) stays here
        on_device = {
            n
            for node in nodes
            for i, n in enumerate(node.inputs)
            if i not in HOST_READ.get(node.op, ())
        } | {o.name for o in self.graph.outputs}
        self.on_host = frozenset(k for k in stored if k in read and k not in on_device)
        self.weights = {
            k: v if k in self.on_host else self.place(v) for k, v in stored.items() if k in read
        }
        self.bound, self.small_inputs = self._shape_bound()
        self.bound_values: dict[tuple, dict[str, torch.Tensor]] = {}
        # of the bound nodes' values, those an unbound node or the caller reads
        read_later = {o.name for o in self.graph.outputs} | {
            n for node, b in zip(self.nodes, self.bound, strict=True) if not b for n in node.inputs
        }
        self.bound_read = {
            n for node, b in zip(self.nodes, self.bound, strict=True) if b for n in node.outputs
        } & read_later
        # after each node, the values no later node reads (an encoder's activations at 1024 px
        # are gigabytes if all are kept)
        kept = set(self.weights) | {o.name for o in self.graph.outputs}
        last = {name: i for i, n in enumerate(self.nodes) for name in n.inputs if name}
        self.free_after: list[list[str]] = [[] for _ in self.nodes]
        for name, i in last.items():
            if name not in kept:
                self.free_after[i].append(name)
        # a call whose shape arithmetic is known walks the other nodes alone (a decoder's are a
        # third of them), each freeing what the bound nodes before it freed too (a Shape may be
        # the last to read an activation)
        self.unbound: list[tuple[int, list[str]]] = []
        skipped: list[str] = []
        for i, bound in enumerate(self.bound):
            if bound:
                skipped += self.free_after[i]
            else:
                self.unbound.append((i, skipped + self.free_after[i]))
                skipped = []

    def _shape_bound(self) -> tuple[list[bool], list[str]]:
        """Which nodes compute the same values whenever the inputs have the same shapes and the
        small inputs (up to 16 values: SAM's `has_mask_input`, `orig_im_size`) the same values:
        shape arithmetic, most of a SAM decoder's nodes. `forward` runs them once per such key.
        A value is known from the key when its node reads known values only, or is a Shape of a
        tensor whose shape is known; a shape is known when its node's output shape follows from
        known shapes (SHAPE_FROM_SHAPES) or from a known first shape and known other values
        (SHAPE_FROM_VALUES); any other operator's output shape counts as unknown."""
        small = [
            v.name
            for v in self.graph.inputs
            if v.shape and all(isinstance(d, int) for d in v.shape) and math.prod(v.shape) <= 16
        ]
        value_known = set(self.weights) | set(small)
        shape_known = value_known | {v.name for v in self.graph.inputs}
        bound = []
        for node in self.nodes:
            ins = [n for n in node.inputs if n]
            if node.op == "Shape":
                values = ins[0] in shape_known
            else:
                values = all(n in value_known for n in ins)
            shapes = values or (
                node.op in SHAPE_FROM_SHAPES
                and all(n in shape_known for n in ins)
                or node.op in SHAPE_FROM_VALUES
                and ins[0] in shape_known
                and all(n in value_known for n in ins[1:])
            )
            bound.append(values)
            value_known.update(node.outputs if values else ())
            shape_known.update(node.outputs if shapes else ())
        return bound, small

    def _key(self, feeds: dict[str, torch.Tensor]) -> tuple:
        """What the shape-bound nodes' values depend on: the inputs' shapes and types, and the
        small inputs' values."""
        shapes = tuple((k, tuple(v.shape), v.dtype) for k, v in sorted(feeds.items()))
        return shapes + tuple(tuple(feeds[k].reshape(-1).tolist()) for k in self.small_inputs)

    @property
    def operators_per_call(self) -> int:
        """Nodes a call runs once its key's shape arithmetic is known."""
        return len(self.nodes) - (sum(self.bound) if self.reuse_shapes else 0)

    def place(
        self,
        t: torch.Tensor,  # [...] an input, a weight or an operator's output
    ) -> torch.Tensor:  # [...] the same, floating ones on the device in the session's type
        """Floating tensors to the device in the session's type; integers stay on the CPU."""
        if t.is_floating_point():
            t = to_device(t, self.device)  # from pinned memory in a capture
            return t if t.dtype == self.dtype else t.to(self.dtype)
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
        key = self._key(feeds)
        if not self.cuda_graphs:
            return self._run(feeds, key)
        replay = self.replays.get(key)
        if replay is None:
            outputs = self._run(feeds, key)  # a new key's shape arithmetic, and the warm-up
            if key not in self.replays and len(self.replays) < MAX_GRAPHS:
                self.replays[key] = self._capture(feeds, key, outputs)
            return outputs
        for name, value in feeds.items():
            replay.inputs[name].copy_(value)
        replay.launch()
        return [o.clone() for o in replay.outputs]

    def _capture(
        self, feeds: dict[str, torch.Tensor], key: tuple, eager: list[torch.Tensor]
    ) -> Replay | None:
        """`key`'s CUDA graph, checked against `eager` (this call's outputs), or None (said)."""
        inputs = {k: self.place(v).clone() for k, v in feeds.items()}
        if not all(t.is_floating_point() for t in inputs.values()):
            return self._refuse(key, "an integer input stays on the CPU")
        copies: dict = {}
        try:
            with device_copies(copies):  # made before the capture, which cannot copy from host
                launch, outputs = self.record(lambda: self._run(inputs, key))
            launch()
            gap = max(
                float((o.float() - e.float()).abs().max())
                for o, e in zip(outputs, eager, strict=True)
            )
        except RuntimeError as exc:
            return self._refuse(key, f"its capture failed ({first_error(exc)})")
        scale = max(float(e.float().abs().max()) for e in eager)
        if not gap <= 1e-3 * max(1.0, scale):
            return self._refuse(key, f"its replay differs from the eager run by {gap:.3g}")
        return Replay(launch, inputs, outputs, (self.bound_values.get(key), copies))

    def _refuse(self, key: tuple, why: str) -> None:
        shapes = ", ".join(
            f"{k} {list(shape)}" for k, shape, _ in key[: len(key) - len(self.small_inputs)]
        )
        warnings.warn(
            f"{self.path.name}: no CUDA graph for inputs of shapes {shapes}: {why}; they run "
            "eagerly",
            stacklevel=4,
        )
        return None

    def _run(self, feeds: dict[str, torch.Tensor], key: tuple) -> list[torch.Tensor]:
        """The graph's nodes, one by one, on `feeds` of `key`."""
        values: dict[str, torch.Tensor | None] = {"": None, **self.weights}
        values.update({k: self.place(v) for k, v in feeds.items()})
        known = self.bound_values.get(key) if self.reuse_shapes else None
        values.update(known or {})
        record: dict[str, torch.Tensor] = {}  # on a new key: the bound values later nodes read
        opset = self.graph.opset
        # the bound nodes' values came with a known key
        steps = self.unbound if known is not None else enumerate(self.free_after)
        for i, free in steps:
            node = self.nodes[i]
            try:
                outs = _run_node(node, [values[name] for name in node.inputs], opset)
            except RuntimeError as exc:  # which node: a capture's refusal names it
                exc.add_note(f"{node.op} -> {node.outputs[0]}")
                raise
            if node.op in ("ConstantOfShape", "Cast"):  # Constants were folded at open
                outs = [self.place(o) if o.is_floating_point() else o for o in outs]
            if self.bound[i]:  # shape arithmetic's integers live on the host (a Cast of a
                # small input on the GPU, say): a later call reads them there without waiting
                outs = [o if o.is_floating_point() else o.cpu() for o in outs]
            for name, value in zip(node.outputs, outs, strict=True):
                values[name] = value
                if name in self.bound_read:
                    record[name] = value
            for name in free:
                values.pop(name, None)
        if known is None and self.reuse_shapes:
            if len(self.bound_values) >= 64:  # prompts of many shapes: keep the latest
                self.bound_values.clear()
            self.bound_values[key] = record
        return [values[o.name] for o in self.graph.outputs]

    def run(self, output_names, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """onnxruntime's `InferenceSession.run`: numpy in, float32 numpy out."""
        outs = self.forward({k: torch.from_numpy(np.asarray(v)) for k, v in feeds.items()})
        names = [o.name for o in self.graph.outputs]
        chosen = names if output_names is None else list(output_names)
        by_name = dict(zip(names, outs, strict=True))
        return to_host([by_name[n].float() for n in chosen])


def to_host(
    tensors: list[torch.Tensor],  # [...] each, on one device
) -> list[np.ndarray]:  # [...] each, the same values
    """Tensors as numpy. From a GPU, the copies are queued together into pinned memory and
    waited for once (each `.cpu()` would wait for the GPU on its own: a decoder call's three
    outputs, three waits); on the CPU they are the tensors themselves."""
    copies = [t.detach().to("cpu", non_blocking=True) for t in tensors]
    device = next((t.device for t in tensors if t.is_cuda), None)
    if device is not None:
        torch.cuda.current_stream(device).synchronize()
    return [c.numpy() for c in copies]


def encoder_runtime(runtime: str, device: str) -> str:
    """What runs a SAM-family half for `segmenter.encoder_runtime` (or `decoder_runtime`) on
    `device`: auto takes onnxruntime unless the device is CUDA, onnxruntime has no CUDA
    provider and PyTorch has CUDA (then torch)."""
    if runtime != "auto":
        return runtime
    if not device.startswith("cuda"):
        return "onnxruntime"
    import onnxruntime as ort

    if "CUDAExecutionProvider" in ort.get_available_providers() or not torch.cuda.is_available():
        return "onnxruntime"
    return "torch"
