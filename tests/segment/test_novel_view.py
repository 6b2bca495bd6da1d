"""The 2D segmenter answering novel views (the paper's initial mode), and the answer modes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from sagonline.refine.service import OnlineSegmentation
from sagonline.render.api import render, to_uint8
from sagonline.score.metrics import view_metrics
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.classical import FlowWatershedSegmenter
from sagonline.segment.novel_view import NovelViewSegmenter
from sagonline.segment.oracle import OracleSegmenter
from sagonline.segment.prompts import Prompt


def _rgb(task, camera):
    return to_uint8(render(task.gaussians, camera, backend="torch").rgb)


def _novel(task, segmenter):
    frames = [_rgb(task, c) for c in task.trajectory]
    return NovelViewSegmenter(
        segmenter, frames, task.trajectory_gt, task.trajectory, task.prompt, task.trajectory_gt
    )


class Recording(VideoSegmenter):
    """Answers its prompt's masks on every frame and remembers what it was given."""

    name = "recording"

    def __init__(self):
        self.calls = []

    def _segment(self, frames, prompt, ground_truth):
        self.calls.append((frames, prompt))
        out = np.zeros(frames[0].shape[:2], np.int64)
        for obj in prompt.objects:
            out[obj.mask] = obj.label
        return [out] * len(frames), None


class TruthSpy(OracleSegmenter):
    """The oracle, remembering the two-frame video's ground truth it was handed."""

    def _segment(self, frames, prompt, ground_truth):
        self.truth = ground_truth
        return super()._segment(frames, prompt, ground_truth)


def test_a_novel_view_hands_the_oracle_the_right_truths(tiny_task):
    """The two-frame video is (nearest other trajectory frame, the novel view): the oracle must
    get that frame's truth first and the view's own truth second, at the view's size, and
    answer the second."""
    spy = TruthSpy()
    novel = _novel(tiny_task, spy)
    for view in tiny_task.eval_views:
        cam = view.camera.scaled(view.camera.width * 2, view.camera.height * 2)  # another size
        mask = novel.answer(_rgb(tiny_task, cam), cam, view.gt)
        k = novel.nearest(cam)
        shape = (cam.height, cam.width)
        first, second = spy.truth
        assert first.shape == second.shape == mask.shape == shape
        assert np.array_equal(
            first,
            cv2.resize(
                tiny_task.trajectory_gt[k].astype(np.uint8),
                shape[::-1],
                interpolation=cv2.INTER_NEAREST,
            ),
        )
        assert np.array_equal(
            second,
            cv2.resize(view.gt.astype(np.uint8), shape[::-1], interpolation=cv2.INTER_NEAREST),
        )
        assert np.array_equal(mask, second)
        assert view_metrics(mask, view.gt, "pred_to_gt")["iou"] == 1.0


def test_the_classical_segmenter_follows_the_object_into_a_novel_view(tiny_task):
    novel = _novel(tiny_task, FlowWatershedSegmenter())
    ious = [
        view_metrics(novel.answer(_rgb(tiny_task, v.camera), v.camera), v.gt, "pred_to_gt")["iou"]
        for v in tiny_task.eval_views
    ]
    assert min(ious) > 0.5, ious


def test_the_prompt_is_the_nearest_other_frame_mask_with_an_interior_click(tiny_task):
    spy = Recording()
    novel = _novel(tiny_task, spy)
    asked = tiny_task.trajectory[2]  # a trajectory view: its own frame is never the prompt
    k = novel.nearest(asked)
    assert k != 2 and tiny_task.trajectory[k].name != asked.name
    novel.answer(_rgb(tiny_task, asked), asked)
    frames, prompt = spy.calls[-1]
    assert len(frames) == 2 and np.array_equal(frames[0], novel.frames[k])
    for obj in prompt.objects:
        x, y = obj.points[0].astype(int)
        assert obj.mask[y, x] and obj.point_labels[0] == 1
        assert np.array_equal(obj.mask, tiny_task.trajectory_gt[k] == obj.label)


def test_a_view_of_another_size_gets_a_prompt_of_its_size(tiny_task):
    spy = Recording()
    novel = _novel(tiny_task, spy)
    view = tiny_task.eval_views[0]
    rgb = cv2.resize(_rgb(tiny_task, view.camera), None, fx=2, fy=2)
    mask = novel.answer(rgb, view.camera)
    frames, prompt = spy.calls[-1]
    assert mask.shape == rgb.shape[:2] and frames[0].shape == rgb.shape
    assert all(
        o.mask.shape == rgb.shape[:2]
        and o.mask[o.points[0, 1].astype(int), o.points[0, 0].astype(int)]
        for o in prompt.objects
    )


def test_objects_lost_at_the_nearest_frame_answer_background_and_text_prompts_pass(tiny_task):
    spy = Recording()
    empty = [np.zeros_like(m) for m in tiny_task.trajectory_gt]
    frames = [_rgb(tiny_task, c) for c in tiny_task.trajectory]
    view = tiny_task.eval_views[0]
    lost = NovelViewSegmenter(spy, frames, empty, tiny_task.trajectory, tiny_task.prompt)
    assert not lost.answer(frames[0], view.camera).any() and not spy.calls
    texts = Prompt(frame=3, texts=["chair"])
    by_text = NovelViewSegmenter(spy, frames, empty, tiny_task.trajectory, texts)
    by_text.answer(frames[0], view.camera)
    assert spy.calls[-1][1] == Prompt(frame=0, texts=["chair"])
    with pytest.raises(ValueError, match="as many frames"):
        NovelViewSegmenter(spy, frames[:2], empty, tiny_task.trajectory, texts)


def test_answer_modes(tiny_task):
    n = tiny_task.gaussians.means.shape[0]
    labels = torch.ones(n, dtype=torch.long)
    view = tiny_task.eval_views[0].camera
    plain = OnlineSegmentation(tiny_task.gaussians, labels, 2)
    assert plain.mode == "coarse" and plain.answer(view).mode == "coarse"
    with pytest.raises(RuntimeError, match="initial mode"):
        plain.answer(view, "initial")
    with pytest.raises(RuntimeError, match="refined mode"):
        plain.answer(view, "refined")
    with pytest.raises(ValueError, match="coarse, initial, refined"):
        plain.answer(view, "instant")
    spy = Recording()
    online = OnlineSegmentation(tiny_task.gaussians, labels, 2, segmenter=_novel(tiny_task, spy))
    answer = online.answer(view)
    assert online.mode == answer.mode == "initial" and answer.ms > 0 and len(spy.calls) == 1
    assert answer.mask.shape == (view.height, view.width)
