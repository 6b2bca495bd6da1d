"""What a CUDA graph's capture forbids, checked on the CPU for the real models' four graphs
(`segmenter.cuda_graphs`, `segment.onnx_torch`): a captured call may neither read a device
tensor's values on the host (a Resize's scales, a Clip's bounds: each a wait on the GPU, which a
capture refuses) nor need shape arithmetic's integers off the host. The device is PyTorch's
`meta`: its tensors have shapes and no values, so any such read raises, naming the node.
Both decoders' captures failed so on an H200 before these rules; the CUDA test that replays
them (`tests/segment/test_onnx_torch.py`) runs there only."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.segment.onnx_device import device_copies
from sagonline.segment.onnx_torch import TorchSession, first_error
from tests.segment.test_sam_family import PAIRS, needs

pytestmark = pytest.mark.xdist_group("onnx_torch")

META = torch.device("meta")


def feeds_for(session: TorchSession) -> dict[str, torch.Tensor]:
    """Inputs of the graph's shapes (a named dimension: 1), a box prompt for a decoder."""
    rng = np.random.default_rng(0)
    given = {
        "orig_im_size": torch.tensor([342.0, 456.0]),
        "point_coords": torch.tensor([[[10.0, 20.0], [100.0, 120.0]]]),
        "point_labels": torch.tensor([[2.0, 3.0]]),
        "has_mask_input": torch.zeros(1),
    }
    feeds = {}
    for value in session.get_inputs():
        shape = [d if isinstance(d, int) else 1 for d in value.shape]
        feeds[value.name] = given.get(value.name, torch.from_numpy(rng.random(shape, np.float32)))
    return feeds


def captured_call_on_meta(session: TorchSession, feeds: dict[str, torch.Tensor]) -> list:
    """A key's call as a capture makes it: its shape arithmetic from an earlier call on the
    CPU, every tensor the session would place on the GPU on `meta` instead, the copies of host
    tensors made once (a warm-up) and reused. Returns the outputs (shapes only)."""
    key = session._key(feeds)
    session._run(feeds, key)  # the key's first call: its shape arithmetic, kept

    def placed(t):
        return t.to(META) if t.is_floating_point() else t

    assert all(
        not t.is_floating_point() or t.device.type == "cpu" for t in session.weights.values()
    )
    session.weights = {
        k: v if k in session.on_host else placed(v) for k, v in session.weights.items()
    }
    bound = session.bound_values[key]
    assert all(t.device.type == "cpu" for t in bound.values() if not t.is_floating_point())
    session.bound_values[key] = {k: placed(v) for k, v in bound.items()}
    session.device = META
    inputs = {k: session.place(v) for k, v in feeds.items()}
    with device_copies({}):
        session._run(inputs, key)  # the warm-up before a capture
        return session._run(inputs, key)  # the captured call


@pytest.mark.parametrize("half", ["encoder", "decoder"])
@pytest.mark.parametrize("kind", [pytest.param(k, marks=needs(k)) for k in PAIRS])
def test_a_captured_call_reads_no_device_value_on_the_host(kind, half):
    path = PAIRS[kind][0 if half == "encoder" else 1]
    session = TorchSession(path, "cpu")
    feeds = feeds_for(session)
    want = [tuple(t.shape) for t in TorchSession(path, "cpu").forward(feeds)]
    got = captured_call_on_meta(session, feeds)
    assert [tuple(t.shape) for t in got] == want
    assert all(t.device == META for t in got)


@pytest.mark.parametrize("kind", [pytest.param("sam2_tiny", marks=needs("sam2_tiny"))])
def test_weights_read_only_on_the_host_stay_there(kind):
    """SAM 2's decoder clips with constant bounds and its encoder resizes by constant scales:
    those weights stay on the CPU, every other floating weight goes to the device."""
    encoder, decoder = (TorchSession(p, "cpu") for p in PAIRS[kind])
    for session, op in ((decoder, "Clip"), (encoder, "Resize")):
        read_on_host = {
            n for node in session.nodes if node.op == op for n in node.inputs[1:] if n
        } & set(session.weights)
        assert read_on_host and read_on_host <= session.on_host
        rest = {n for node in session.nodes if node.op == "Conv" for n in node.inputs[1:] if n}
        assert rest and not rest & session.on_host


def test_the_meta_device_catches_a_host_read_of_a_device_value(tmp_path):
    """The check can fail: a Clip whose bounds are computed from an input (not constants)
    reads device values on the host, and the captured call says which node."""
    from onnx import TensorProto, helper

    from tests.segment.test_onnx_torch import model_file

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [4, 5])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [4, 5])
    nodes = [
        helper.make_node("ReduceMax", ["x"], ["high"], keepdims=0),
        helper.make_node("Clip", ["x", "", "high"], ["y"]),
    ]
    path = model_file(tmp_path, nodes, [x], [y], opset=17)
    session = TorchSession(path, "cpu")
    with pytest.raises(RuntimeError) as raised:
        captured_call_on_meta(session, {"x": torch.ones(4, 5)})
    assert first_error(raised.value).startswith("Clip -> y; ")


def test_a_capture_refusal_names_the_error_that_began_it():
    """A capture's end raises its own error over the one inside it; the refusal names both,
    the first with its node."""
    try:
        try:
            inner = RuntimeError("cannot read a tensor on the host\nmore")
            inner.add_note("Clip -> y")
            raise inner
        except RuntimeError:
            raise RuntimeError("operation failed due to a previous error during capture")  # noqa: B904
    except RuntimeError as exc:
        said = first_error(exc)
    assert said == (
        "Clip -> y; cannot read a tensor on the host; "
        "then: operation failed due to a previous error during capture"
    )
    alone = RuntimeError("out of memory")
    assert first_error(alone) == "out of memory"
