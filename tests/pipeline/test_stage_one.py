"""Stage I's engine: the events it streams, stop and resume, prompts of every kind on any view,
the cache streamed back, the frame selection every mask policy obeys, one label encoding."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sagonline.core.errors import PromptError
from sagonline.pipeline.graph import StageCache
from sagonline.pipeline.segment import segmenter_run_of
from sagonline.pipeline.stage_one import (
    FrameRendered,
    LabelsUpdated,
    MaskReady,
    PipelineSettings,
    StageOne,
    StageOneConfig,
    ViewVoted,
)
from sagonline.segment.classical import FlowWatershedSegmenter
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig, consensus_vote
from sagonline.vote.feedback import FeedbackConfig


def engine_for(
    task, *, segmenter=None, vote=None, cache=None, publish_every=None, prompt=True, **settings
):
    """An engine on `task`, prompted with the task's prompt (prompt=False: none yet)."""
    run = segmenter_run_of(segmenter or OracleSegmenter())
    config = StageOneConfig(
        task.gaussians,
        task.trajectory,
        run,
        vote or VoteConfig(),
        PipelineSettings(progress=False, **settings),
        task.num_labels,
        task.trajectory_gt,
        cache,
        publish_every,
    )
    return StageOne(config, task.prompt if prompt else None)


def test_events_come_in_the_data_flow_order(tiny_task):
    engine = engine_for(tiny_task, publish_every=2)
    events = list(engine.stream())
    n = len(tiny_task.trajectory)
    kinds = [type(e).__name__ for e in events]
    assert kinds[:n] == ["FrameRendered"] * n  # every frame before any mask (the video)
    masks = [e for e in events if isinstance(e, MaskReady)]
    assert masks[0].index == tiny_task.prompt.frame and len(masks) == n
    voted = [e for e in events if isinstance(e, ViewVoted)]
    assert [v.voted for v in voted] == list(range(1, n + 1))
    updates = [e for e in events if isinstance(e, LabelsUpdated)]
    assert [u.voted for u in updates] == [1, 3, 5, n][: len(updates) - 1] + [n]
    assert updates[-1].final and not any(u.final for u in updates[:-1])
    final = updates[-1].labels
    assert final.dtype == np.int64 and final.min() >= -1  # one encoding: -1 unlabelled
    assert np.array_equal(final, engine.result().labels)


def test_the_engine_votes_as_the_one_call_vote_does(tiny_task):
    out = engine_for(tiny_task).run()
    ref = consensus_vote(
        tiny_task.gaussians, tiny_task.trajectory, tiny_task.trajectory_gt, tiny_task.num_labels
    )
    assert np.array_equal(out.labels, ref.labels.numpy())
    assert out.vote.value.stats["votes_cast"] == ref.stats["votes_cast"] > 0


def test_stop_and_resume_give_the_uninterrupted_labels(tiny_task):
    whole = engine_for(tiny_task).run().labels
    engine = engine_for(tiny_task)
    seen = 0
    for event in engine.stream():
        if isinstance(event, ViewVoted):
            seen += 1
            if seen == 3:
                engine.stop()
    assert not engine.done and engine.voted == 3
    assert (engine.vote_so_far().labels >= 0).any()
    for _ in engine.stream():  # resumed where it stopped
        pass
    assert engine.done and np.array_equal(engine.result().labels, whole)


@pytest.mark.parametrize("kind", ["points", "box", "mask"])
def test_a_prompt_of_any_kind_on_any_view(tiny_task, kind):
    frame = 2
    gt = tiny_task.trajectory_gt[frame]
    ys, xs = np.nonzero(gt == 1)
    given = {
        "points": {"points": [(xs[len(xs) // 2] + 0.5, ys[len(ys) // 2] + 0.5)]},
        "box": {"box": [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]},
        "mask": {"mask": gt == 1},
    }[kind]
    engine = engine_for(tiny_task, segmenter=FlowWatershedSegmenter(), prompt=False)
    assert engine.add_prompt(frame, name="thing", **given) == 1
    assert engine.prompt.frame == frame and engine.prompt.names == ["background", "thing"]
    out = engine.run()
    labelled = out.labels == 1
    assert labelled.any()
    truth = tiny_task.gt_labels3d.numpy()
    assert (truth[labelled] == 1).mean() > 0.8


def test_prompts_grow_an_object_and_stay_on_one_view(tiny_task):
    engine = engine_for(tiny_task, prompt=False)
    label = engine.add_prompt(0, points=[(5.0, 5.0)])
    assert engine.add_prompt(0, points=[(6.0, 6.0)], point_labels=[0], obj_id=label) == label
    obj = engine.prompt.objects[0]
    assert obj.points.tolist() == [[5.0, 5.0], [6.0, 6.0]] and obj.point_labels.tolist() == [1, 0]
    with pytest.raises(PromptError, match="on view 0"):
        engine.add_prompt(1, points=[(1.0, 1.0)])
    with pytest.raises(PromptError, match="out of range"):
        engine.add_prompt(99, points=[(1.0, 1.0)])
    with pytest.raises(PromptError, match="no object 7"):
        engine.add_prompt(0, points=[(1.0, 1.0)], obj_id=7)


def test_a_cached_run_streams_the_cache_and_says_so(tiny_task, tmp_path):
    first = engine_for(tiny_task, cache=StageCache(tmp_path)).run()
    engine = engine_for(tiny_task, cache=StageCache(tmp_path))
    events = list(engine.stream())
    assert all(e.cached for e in events if isinstance(e, (FrameRendered, MaskReady)))
    assert not [e for e in events if isinstance(e, ViewVoted)]  # the vote came from the cache
    assert {k: v.status for k, v in engine.result().runs.items()} == dict.fromkeys(
        ("frames", "masks", "vote"), "cached"
    )
    assert np.array_equal(engine.result().labels, first.labels)


def test_an_interrupted_stream_saves_only_whole_stages(tiny_task, tmp_path):
    engine = engine_for(tiny_task, cache=StageCache(tmp_path))
    for event in engine.stream():
        if isinstance(event, MaskReady):
            engine.stop()
    names = sorted(p.name.split("-")[0] for p in tmp_path.iterdir())
    assert names == ["frames"]  # the masks and the vote were not finished


def test_feedback_votes_only_the_selected_frames(tiny_task):
    """Consensus feedback is a mask policy under the run's own frame selection: with stride 3
    the views between never vote (the old loop voted them all)."""
    vote = VoteConfig(stride=3)
    feedback = FeedbackConfig(enabled=True, every=2, min_frames=1)
    engine = engine_for(tiny_task, segmenter=FlowWatershedSegmenter(), vote=vote, feedback=feedback)
    out = engine.run()
    selected = set(range(0, len(tiny_task.trajectory), 3))
    assert set(out.vote.value.frames) == selected
    assert "feedback" in out.masks.value.info


def test_the_label_count_grows_with_the_masks(tiny_task):
    """A segmenter may name more objects than the task knows: the vote makes room for them."""
    task = dataclasses.replace(tiny_task, num_labels=1)
    out = engine_for(task).run()
    assert out.num_labels == tiny_task.num_labels and out.labels.max() == task.num_labels
