"""Consensus feedback: a segmenter that loses the object is re-prompted from the fused labels."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from sagonline.datasets.synthetic import load_synthetic
from sagonline.pipeline import PipelineSettings, run_scene
from sagonline.segment.base import VideoSegmenter
from sagonline.vote.consensus import VoteConfig
from sagonline.vote.feedback import FeedbackConfig, foreground_iou, mask_prompt


class ForgetfulSegmenter(VideoSegmenter):
    """Right for `memory` frames after its prompt frame, then the object is lost (empty masks).
    Reads the ground truth as the oracle does, to be right while it remembers."""

    name = "forgetful"

    def __init__(self, memory: int = 2):
        self.memory, self.prompts = memory, []

    def _segment(self, frames, prompt, ground_truth):
        self.prompts.append(prompt)
        out = []
        for t, gt in enumerate(ground_truth):
            near = abs(t - prompt.frame) <= self.memory
            out.append(np.asarray(gt, np.int64) if near else np.zeros(gt.shape, np.int64))
        return out, None


def test_helpers():
    a = np.array([[0, 1], [1, 2]])
    assert foreground_iou(a, a) == 1.0 and foreground_iou(a * 0, a * 0) == 1.0
    assert foreground_iou(a, np.zeros_like(a)) == 0.0
    p = mask_prompt(a, 3)
    assert p.frame == 3 and [o.label for o in p.objects] == [1, 2]
    assert (p.objects[1].mask == (a == 2)).all()


def test_feedback_brings_a_lost_object_back():
    task = load_synthetic(
        layout="forward", num_gaussians=1500, width=40, height=30, num_train_views=12
    )[0]
    off_seg, on_seg = ForgetfulSegmenter(), ForgetfulSegmenter()
    off, _ = run_scene(task, off_seg, VoteConfig(), PipelineSettings(progress=False))
    feedback = FeedbackConfig(enabled=True, every=2, min_frames=2, min_iou=0.5)
    on, out = run_scene(
        task, on_seg, VoteConfig(), PipelineSettings(progress=False, feedback=feedback)
    )
    assert len(off_seg.prompts) == 1 and off.extra.get("feedback") is None
    stats = on.extra["feedback"]
    assert stats["restarts"] >= 2 and len(on_seg.prompts) == 1 + stats["restarts"]
    assert all(p.objects and p.objects[0].mask is not None for p in on_seg.prompts[1:])
    masks = out.masks.value.masks
    lost = [t for t in range(len(masks)) if t > task.prompt.frame + 2]
    assert all(masks[t].any() for t in lost)  # every frame sees the object again
    assert on.segmenter_miou > off.segmenter_miou + 0.2
    assert on.miou > off.miou


def test_the_advice_is_rendered_small_and_enlarged_to_the_view():
    from sagonline.segment.mask_geometry import box_of
    from sagonline.vote.consensus import VoteAccumulator
    from sagonline.vote.feedback import FeedbackInputs, FusedRender

    task = load_synthetic(layout="forward", num_gaussians=1500, width=96, height=64)[0]
    g, views, truth = task.gaussians, task.trajectory, task.trajectory_gt
    votes = VoteAccumulator(len(g), task.num_labels, VoteConfig())
    for t in range(4):
        votes.add_view(g, views[t], truth[t], backend="native")
    setup = FeedbackInputs(FeedbackConfig(), VoteConfig(), g, views, task.num_labels, 0.2, "native")
    full = FusedRender(setup, votes, after=4)(5)
    small = FusedRender(replace(setup, render_side=48), votes, after=4)(5)  # half the view
    assert full is not None and small is not None
    assert small.shape == full.shape == (64, 96)
    # enlarged twice, nearest: each rendered pixel fills its 2 x 2 block of the view
    assert (small == small[::2, ::2].repeat(2, axis=0).repeat(2, axis=1)).all()
    assert set(np.unique(small)) <= set(np.unique(full))
    assert foreground_iou(small, full) > 0.7
    for k in np.unique(full[full > 0]):  # each object's box within two rendered pixels
        assert np.abs(box_of(small == k) - box_of(full == k)).max() <= 4
    assert FusedRender(setup, votes, after=5)(5) is None  # before `after` views voted
