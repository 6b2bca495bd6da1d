"""Segmenter plug-ins: the classical one for real, model-backed ones with random weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bench.runners.eval import prepare_segmenter
from sagonline.score.metrics import match_labels, relabel, view_metrics
from sagonline.segment import ObjectPrompt, Prompt
from sagonline.segment.classical import ClassicalConfig, FlowWatershedSegmenter, remember
from sagonline.segment.compat import nms_reference
from sagonline.segment.sam3_text import SAM3TextSegmenter, merge_text_masks
from sagonline.segment.yolo import TrackLabeler
from tests.fixtures import (
    compose_config,
)


def segmenter_from(name: str, *overrides):
    cfg = compose_config("eval", *[f"segmenter={name}", *overrides])
    return prepare_segmenter(cfg.segmenter).segmenter


def rendered(task) -> list[np.ndarray]:
    """The task's trajectory rendered by Stage I's engine (its frames, no segmenting)."""
    from sagonline.pipeline.segment import segmenter_run_of
    from sagonline.pipeline.stage_one import StageOne, StageOneConfig
    from sagonline.segment.oracle import OracleSegmenter

    run = segmenter_run_of(OracleSegmenter())
    return StageOne(StageOneConfig(task.gaussians, task.trajectory, run)).render()


@pytest.fixture(scope="module")
def video():
    from sagonline.datasets.synthetic import load_synthetic

    task = load_synthetic(
        layout="360",
        num_objects=3,
        num_gaussians=6000,
        width=128,
        height=96,
        num_train_views=16,
        num_eval_views=2,
        seed=2,
    )[0]
    return task, rendered(task)


def test_classical_tracks_objects_through_the_orbit(video):
    task, frames = video
    seg = segmenter_from("classical")
    from sagonline.datasets.common import click_prompt

    prompt = click_prompt(task.trajectory_gt[5], 5, task.num_labels, 3, seed=0)
    res = seg.segment(frames, prompt, ground_truth=None)
    ious = [view_metrics(m, g)["iou"] for m, g in zip(res.masks, task.trajectory_gt, strict=True)]
    assert np.mean(ious) > 0.8, ious
    assert ious[5] > 0.99  # the prompt frame keeps the given masks
    assert len(res.seconds) == 16 and res.ms_per_frame > 0


def test_classical_grabcut_from_clicks_on_a_single_object():
    from sagonline.datasets.synthetic import load_synthetic

    task = load_synthetic(
        layout="forward",
        num_gaussians=5000,
        width=128,
        height=96,
        num_train_views=6,
        num_eval_views=1,
    )[0]
    frames = rendered(task)
    res = FlowWatershedSegmenter(use_masks=False).segment(frames, task.prompt)
    ious = [view_metrics(m, g)["iou"] for m, g in zip(res.masks, task.trajectory_gt, strict=True)]
    assert min(ious) > 0.8, ious


def card_video(n: int = 12):
    """A red disc standing still on noise, and a grey card sliding over it from the left
    (frames 5 and 6 hide it whole): the frames (n, 64, 96, 3) and the disc's truth masks."""
    import cv2

    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.integers(40, 140, (64, 96, 3)).astype(np.uint8), (5, 5), 0)
    frames, truth = [], []
    for t in range(n):
        frame, disc = noise.copy(), np.zeros((64, 96), np.uint8)
        cv2.circle(disc, (48, 32), 9, 1, -1)
        frame[disc > 0] = (220, 40, 40)
        card = np.s_[:, max(8 * t - 10, 0) : max(8 * t + 24, 0)]
        frame[card], disc[card] = (128, 128, 128), 0
        frames.append(frame)
        truth.append(disc)
    return frames, truth


def test_classical_recovers_an_object_the_flow_lost():
    """Hidden whole for two frames, the disc comes back with `recover` (where its colour does,
    in the region it had before it collapsed) and stays lost without it; the frames before
    are the same. A collapsed region is not remembered."""
    frames, truth = card_video()
    prompt = Prompt(objects=[ObjectPrompt(label=1, mask=truth[0] > 0)], frame=0)
    kept = FlowWatershedSegmenter().segment(frames, prompt).masks
    lost = FlowWatershedSegmenter(recover=0).segment(frames, prompt).masks
    assert [int((m == 1).sum()) for m in lost[5:]] == [0] * 7
    ious = [view_metrics(m, g)["iou"] for m, g in zip(kept[7:], truth[7:], strict=True)]
    assert min(ious) > 0.9, ious
    assert all(np.array_equal(a, b) for a, b in zip(kept[:7], lost[:7], strict=True))
    whole, speck = truth[0].astype(np.int64), np.zeros((64, 96), np.int64)
    speck[32, 48] = 1
    assert remember({1: whole == 1}, speck, 0.5)[1].sum() == whole.sum()
    assert remember({1: whole == 1}, speck, 0.0)[1].sum() == 1
    with pytest.raises(ValueError, match="recover"):
        ClassicalConfig(recover=2)


def test_the_click_colour_is_its_first_form_for_every_pixel_sum():
    """`chromaticity_and_brightness` a plane at a time gives the values of the interleaved
    form, on an image holding every sum of r, g and b (3 to 768 with the + 1s): each log and
    each ratio the first form could take."""
    from sagonline.segment.classical import chromaticity_and_brightness

    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (200, 300, 3), np.uint8)
    frame[0, :256] = [[v, 0, 0] for v in range(256)]  # sums 0 .. 255
    frame[1, :256] = [[255, v, 0] for v in range(256)]  # 255 .. 510
    frame[2, :256] = [[255, 255, v] for v in range(256)]  # 510 .. 765
    assert set(np.unique(frame.astype(int).sum(-1))) == set(range(766))
    first = frame.astype(np.float32) + 1.0
    total = first.sum(-1, keepdims=True)
    want = np.concatenate([first[..., :2] / total, np.log(total)], -1).astype(np.float32)
    got = chromaticity_and_brightness(frame)
    assert got.dtype == np.float32 and got.shape == frame.shape
    np.testing.assert_array_equal(got, want)
    # a view of another layout (flipped, its channels reversed) as its contiguous copy
    flipped = frame[:, ::-1, ::-1]
    np.testing.assert_array_equal(
        chromaticity_and_brightness(flipped),
        chromaticity_and_brightness(np.ascontiguousarray(flipped)),
    )


def test_classical_rejects_text_only_prompts():
    with pytest.raises(ValueError, match="clicks, boxes or masks"):
        FlowWatershedSegmenter().segment([np.zeros((8, 8, 3), np.uint8)], Prompt(texts=["car"]))


def test_nms_reference():
    boxes = torch.tensor([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 9.0]])
    scores = torch.tensor([0.5, 0.9, 0.7, 0.6])
    assert nms_reference(boxes, scores, 0.5).tolist() == [1, 2]
    assert nms_reference(boxes, scores, 0.99).tolist() == [1, 2, 3, 0]
    assert nms_reference(boxes[:0], scores[:0], 0.5).numel() == 0


def test_track_labeler_keeps_ids_stable():
    lab = TrackLabeler()
    sq = lambda x: np.array([[x, 0], [x + 4, 0], [x + 4, 4], [x, 4]], float)  # noqa: E731
    a = lab.rasterize((8, 20), [sq(0), sq(10)], [7, 3], [0.9, 0.8])
    b = lab.rasterize((8, 20), [sq(12), sq(1), sq(5)], [3, 7, None], [0.8, 0.9, 0.99])
    assert a[2, 2] == 1 and a[2, 12] == 2  # first appearance order
    assert b[2, 13] == 2 and b[2, 2] == 1 and b[2, 7] == 0  # unconfirmed track left out


def test_match_labels_for_automatic_ids():
    gt = [np.array([[1, 1, 2, 2, 0]]), np.array([[2, 2, 1, 1, 0]])]
    pred = [np.array([[5, 5, 3, 3, 4]]), np.array([[3, 3, 5, 5, 0]])]
    mapping = match_labels(pred, gt)
    assert mapping[5] == 1 and mapping[3] == 2 and mapping[4] == 3  # 4 unmatched: fresh id
    assert relabel(pred[0], mapping).tolist() == [[1, 1, 2, 2, 3]]


@pytest.mark.parametrize(
    "name,option",
    [
        ("sam2", "segmenter.checkpoint"),
        ("yolo", "segmenter.weights"),
        ("sam3", "segmenter.checkpoint"),
    ],
)
@pytest.mark.slow
def test_model_backed_segmenters_name_the_missing_option(name, option, capsys):
    cfg = compose_config("eval", *[f"segmenter={name}"])
    with pytest.raises(SystemExit):
        prepare_segmenter(cfg.segmenter)
    err = capsys.readouterr().err
    assert option in err
    # sam2 has no make target for its checkpoint: it names the same model's ONNX files
    assert name != "sam2" or "segmenter=sam2_tiny, after `make weights`" in err
    cfg = compose_config("eval", *[f"segmenter={name}", f"{option}=/nope.pt"])
    with pytest.raises(SystemExit):
        prepare_segmenter(cfg.segmenter)
    assert f"{option}=/nope.pt: no such file" in capsys.readouterr().err


@pytest.mark.slow
def test_sam2_random_weights_tiny_video():
    pytest.importorskip("sam2", reason="install the sam2 extra")
    from sagonline.segment.sam2_video import SAM2VideoSegmenter

    torch.manual_seed(0)
    seg = SAM2VideoSegmenter(allow_random_weights=True, image_size=256)
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (40, 56, 3), dtype=np.uint8) for _ in range(4)]
    prompt = Prompt(
        frame=2,
        objects=[
            ObjectPrompt(label=1, points=np.array([[10.0, 10.0]]), point_labels=np.array([1])),
            ObjectPrompt(label=2, box=np.array([30.0, 5.0, 50.0, 30.0])),
        ],
    )
    res = seg.segment(frames, prompt)
    assert len(res.masks) == 4 and all(m.shape == (40, 56) for m in res.masks)
    assert set(np.unique(np.concatenate([m.ravel() for m in res.masks]))) <= {0, 1, 2}


def test_sam2_checkpoint_must_fit_the_config(tmp_path):
    pytest.importorskip("sam2", reason="install the sam2 extra")
    from sagonline.segment.sam2_video import SAM2VideoSegmenter

    bad = tmp_path / "bad.pt"
    torch.save({"model": {"not_a_key": torch.zeros(1)}}, bad)
    with pytest.raises(RuntimeError, match="does not fit"):
        SAM2VideoSegmenter(checkpoint=str(bad), image_size=256).build()


def test_yolo_random_weights_tracks_tiny_video():
    pytest.importorskip("ultralytics", reason="install the yolo extra")
    from sagonline.segment.yolo import YOLOSegmenter

    torch.manual_seed(0)
    seg = YOLOSegmenter(model_yaml="yolo11n-seg.yaml", classes=None, imgsz=96, conf=0.001)
    frames = [
        np.random.default_rng(i).integers(0, 255, (64, 96, 3), dtype=np.uint8) for i in range(3)
    ]
    res = seg.segment(frames, Prompt())
    assert [m.shape for m in res.masks] == [(64, 96)] * 3
    with pytest.raises(ValueError, match="not one of the model's"):
        seg.segment(frames, Prompt(texts=["unicorn"]))


def test_sam3_label_map_and_requirements(tmp_path):
    m1 = np.zeros((1, 4, 4), bool)
    m1[0, :2] = True
    m2 = np.zeros((2, 4, 4), bool)
    m2[0, 1:3] = True
    m2[1, 3:] = True
    out = merge_text_masks((4, 4), [(m1, np.array([0.9])), (m2, np.array([0.6, 0.3]))], 0.5)
    assert out[:, 0].tolist() == [1, 1, 2, 0]  # row 1: 0.9 beats 0.6; the 0.3 instance dropped
    ckpt = tmp_path / "sam3.pt"
    ckpt.write_bytes(b"0")
    seg = SAM3TextSegmenter(checkpoint=str(ckpt), device="cpu")
    with pytest.raises(RuntimeError, match="needs CUDA"):
        seg.build()


def test_a_segmenters_answers_are_kept_at_the_narrowest_width_that_holds_their_ids():
    """`label_map`: uint8 for ids in [0, 255], uint16 up to 65535, int64 otherwise (a negative
    id stays for the vote to refuse); the values never change. `segment` and `stream` keep
    their answers so (a byte a pixel, not eight), and the run's masks digest is the one int64
    masks had."""
    from sagonline.core.provenance import digest_arrays
    from sagonline.segment.base import VideoSegmenter, label_map

    cases = {
        np.uint8: np.array([[0, 3], [255, 1]], np.int64),
        np.uint16: np.array([[0, 256], [65535, 1]], np.int32),
        np.int64: np.array([[0, -1], [2, 1]], np.int64),
    }
    for dtype, ids in cases.items():
        narrow = label_map(ids)
        assert narrow.dtype == dtype and np.array_equal(narrow, ids)
    assert label_map(np.array([[0, 65536]])).dtype == np.int64
    assert label_map(np.array([[True, False]])).dtype == np.uint8
    kept = np.zeros((2, 2), np.uint8)
    assert label_map(kept) is kept

    class Answers(VideoSegmenter):
        name = "answers"

        def _segment(self, frames, prompt, ground_truth):
            return [np.full(f.shape[:2], 300 * t, np.int64) for t, f in enumerate(frames)], None

    frames = [np.zeros((4, 5, 3), np.uint8)] * 2
    prompt = Prompt(frame=0, objects=[ObjectPrompt(label=1, points=np.array([[1.0, 1.0]]))])
    result = Answers().segment(frames, prompt)
    assert [m.dtype for m in result.masks] == [np.uint8, np.uint16]
    streamed = {i: m for i, m, _ in Answers().stream(frames, prompt)}
    assert streamed[0].dtype == np.uint8 and int(streamed[1].max()) == 300
    wide = [np.asarray(m, np.int64) for m in result.masks]
    assert digest_arrays(result.masks, as_int64=True) == digest_arrays(wide)
