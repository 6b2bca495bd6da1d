"""The vote rules, checked on hand-built traces and on a tiny rendered scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.render import TraceChunk, TraceRequest
from sagonline.render._torch_impl import add_pairs
from sagonline.vote.consensus import (
    MaskError,
    VoteAccumulator,
    VoteConfig,
    check_mask,
    consensus_vote,
    select_frames,
)
from tests.fixtures import small_camera


def chunk(pixel, gaussian, T, alpha, dist):
    t = lambda v, dt=torch.float32: torch.tensor(v, dtype=dt)  # noqa: E731
    return TraceChunk(t(pixel, torch.long), t(gaussian, torch.long), t(T), t(alpha), t(dist))


def streamed(acc, mask, c):
    """Feed `c` as the reference vote does: the renderer keeps the pairs the method's rule
    asks for (`TraceRequest.keeps`), `add_pairs` adds them to the histogram."""
    rule = acc.rule
    request = TraceRequest(print, eps=rule.eps, delta=rule.delta)
    keep = request.keeps(c.transmittance, c.alpha, c.distance**2)
    kept = TraceChunk(*(getattr(c, f)[keep] for f in TraceChunk.__dataclass_fields__))
    add_pairs(acc.hist, mask, kept, rule.weighting)


def stream_four_gaussians(acc):
    """Four Gaussians over four pixels of labels [1, 2, 2, 0]:
    gaussian 0: visible and aligned at pixel 0 (T 1.0, alpha 0.5) -> votes 1
    gaussian 1: T below eps -> no vote;  gaussian 2: centre 3 px away -> no vote
    gaussian 3: votes twice for 2 (pixels 1, 2; T 0.5, 0.4) and once for 0 (pixel 3; T 0.3)."""
    streamed(
        acc,
        torch.tensor([1, 2, 2, 0]),
        chunk(
            [0, 0, 0, 1, 2, 3],
            [0, 1, 2, 3, 3, 3],
            [1.0, 0.005, 0.9, 0.5, 0.4, 0.3],
            [0.5, 0.9, 0.9, 0.5, 0.5, 0.5],
            [0.5, 0.5, 3.0, 1.0, 1.9, 0.1],
        ),
    )


def test_rgc_votes_only_visible_aligned_gaussians():
    acc = VoteAccumulator(4, 3, VoteConfig(margin=0.0))
    stream_four_gaussians(acc)
    assert acc.hist.tolist() == [[0, 1, 0], [0, 0, 0], [0, 0, 0], [1, 0, 2]]
    assert acc.labels().tolist() == [1, -1, -1, 2]  # -1: unlabelled, the one encoding


def test_labels_are_decided_once_per_histogram_and_again_after_any_change(monkeypatch):
    """Stage I reads the labels after each view's vote and again for the next view's advice:
    the second read is the first's tensor; a vote, more labels, a histogram changed in place or
    replaced, and other settings each decide them again."""
    from sagonline.vote import consensus

    acc = VoteAccumulator(4, 3, VoteConfig(margin=0.0))
    stream_four_gaussians(acc)
    first = acc.labels()
    assert acc.labels() is first and first.tolist() == [1, -1, -1, 2]
    acc.hist[1, 2] += 5  # in place
    assert acc.labels().tolist() == [1, 2, -1, 2]
    acc.hist = torch.tensor([[0, 3, 0], [1, 1, 0], [0, 3, 2], [0, 2, 0]], dtype=torch.float64)
    assert acc.labels().tolist() == [1, -1, 1, 1]  # replaced
    acc.cfg = VoteConfig(margin=0.3)  # other settings: 3:2 is now ambiguous
    assert acc.labels().tolist() == [1, -1, -1, 1]
    acc.grow(4)
    assert acc.labels().tolist() == [1, -1, -1, 1] and acc.hist.shape == (4, 4)

    def vote_unseen(gaussians, camera, labels, rule, hist, backend):  # as a GPU kernel writes:
        hist.numpy()[1, 3] += 9  # behind PyTorch's back (no in-place version counted)
        return 1

    monkeypatch.setattr(consensus, "vote_into", vote_unseen)
    camera = small_camera()
    acc.add_view(None, camera, np.zeros((camera.height, camera.width), np.int64), "native")
    assert acc.labels().tolist() == [1, 3, -1, 1]


def test_rgc_blend_weighs_the_same_pairs_by_alpha_times_transmittance():
    """weighting=blend: the same visible, aligned pairs as the paper's count, each adding its
    blend weight alpha_i T_i; min_votes is then a total weight (gaussian 0's 0.5 is too little
    for min_votes=1)."""
    acc = VoteAccumulator(4, 3, VoteConfig(margin=0.0, weighting="blend"))
    stream_four_gaussians(acc)
    expected = [[0, 0.5, 0], [0, 0, 0], [0, 0, 0], [0.15, 0, 0.45]]
    assert torch.allclose(acc.hist, torch.tensor(expected, dtype=acc.hist.dtype))
    assert acc.labels().tolist() == [-1, -1, -1, -1]  # no total reaches one vote's weight
    blend = VoteAccumulator(4, 3, VoteConfig(margin=0.0, weighting="blend", min_votes=1))
    blend.hist += torch.tensor(
        [[0, 2.0, 0], [0, 0, 0], [0, 0, 0], [0.9, 0, 1.2]], dtype=blend.hist.dtype
    )
    assert blend.labels().tolist() == [1, -1, -1, 2]
    with pytest.raises(ValueError, match="weighting='votes'"):
        VoteConfig(weighting="votes")
    with pytest.raises(ValueError, match="does not read weighting"):
        VoteConfig(method="flashsplat", weighting="blend")


def test_min_votes_margin_and_ties():
    hist_rows = [[0, 3, 0], [1, 1, 0], [0, 3, 2], [0, 2, 0]]

    def run(cfg):
        acc = VoteAccumulator(4, 3, cfg)
        acc.hist = torch.tensor(hist_rows, dtype=torch.float64)
        return acc.labels()

    assert run(VoteConfig(margin=0.0)).tolist() == [1, -1, 1, 1]  # the tie is ambiguous
    assert run(VoteConfig(margin=0.3)).tolist() == [1, -1, -1, 1]  # 3:2 is a 0.2 share gap
    assert run(VoteConfig(margin=0.0, min_votes=3)).tolist() == [1, -1, 1, -1]


def test_flashsplat_and_weighted_mean_use_blend_weights():
    c = chunk([0, 1, 1], [0, 0, 1], [1.0, 0.5, 0.2], [0.8, 0.4, 0.5], [9.0, 9.0, 9.0])
    mask = torch.tensor([1, 0])
    fs = VoteAccumulator(2, 2, VoteConfig(method="flashsplat"))
    streamed(fs, mask, c)
    assert fs.hist[0].tolist() == pytest.approx([0.2, 0.8])  # distance is ignored
    assert fs.labels().tolist() == [1, 0]
    fs.cfg = VoteConfig(method="flashsplat", background_slack=0.7)
    assert fs.labels().tolist() == [0, 0]
    wm = VoteAccumulator(2, 2, VoteConfig(method="weighted_mean", threshold=0.75))
    streamed(wm, mask, c)
    assert wm.labels().tolist() == [1, 0]  # 0.8 >= 0.75
    wm.cfg = VoteConfig(method="weighted_mean", threshold=0.9)
    assert wm.labels().tolist() == [0, 0]


def test_select_frames():
    assert select_frames(10, VoteConfig()) == list(range(10))
    assert select_frames(10, VoteConfig(stride=3)) == [0, 3, 6, 9]
    assert select_frames(10, VoteConfig(num_masks=3)) == [0, 4, 9]
    assert select_frames(10, VoteConfig(num_masks=3, selection="first")) == [0, 1, 2]
    r1 = select_frames(100, VoteConfig(num_masks=5, selection="random", seed=1))
    assert r1 == select_frames(100, VoteConfig(num_masks=5, selection="random", seed=1))
    assert r1 != select_frames(100, VoteConfig(num_masks=5, selection="random", seed=2))
    assert len(set(r1)) == 5


def test_mask_errors_name_the_frame():
    cam = small_camera(8, 6)
    with pytest.raises(MaskError, match=r"frame 3.*\(5, 8\).*6x8"):
        check_mask(np.zeros((5, 8), int), cam, 2, "mask of frame 3")
    with pytest.raises(MaskError, match=r"\[0, 2\).*\[7, 7\]"):
        check_mask(np.full((6, 8), 7), cam, 2, "mask of frame 0")
    with pytest.raises(MaskError, match="non-integer"):
        check_mask(np.full((6, 8), 0.5), cam, 2, "m")
    assert check_mask(np.ones((6, 8), bool), cam, 2, "m").sum() == 48


def test_bad_config_rejected():
    with pytest.raises(ValueError, match="consensus.method='median': must be one of"):
        VoteConfig(method="median")
    with pytest.raises(ValueError, match="selection"):
        VoteConfig(selection="every")


@pytest.fixture(scope="module")
def tiny_task():
    from sagonline.datasets.synthetic import load_synthetic

    return load_synthetic(
        preset="t",
        layout="360",
        num_objects=3,
        num_gaussians=6000,
        width=96,
        height=72,
        num_train_views=12,
        num_eval_views=3,
        seed=3,
    )[0]


@pytest.mark.parametrize(
    "method,floor", [("rgc", 0.97), ("flashsplat", 0.9), ("weighted_mean", 0.8)]
)
def test_vote_on_rendered_scene(tiny_task, method, floor):
    t = tiny_task
    res = consensus_vote(
        t.gaussians, t.trajectory, t.trajectory_gt, t.num_labels, VoteConfig(method=method)
    )
    ok = res.labels >= 0
    acc = float((res.labels[ok] == t.gt_labels3d[ok]).float().mean())
    assert acc > floor, acc
    assert 0.3 < res.stats["fraction_labelled"] <= 1.0
    assert res.stats["num_masks"] == 12 and res.histogram.shape == (len(t.gaussians), 4)


def test_rgc_eps_controls_depth_of_voting(tiny_task):
    t = tiny_task
    crust = consensus_vote(
        t.gaussians, t.trajectory, t.trajectory_gt, t.num_labels, VoteConfig(eps=0.5)
    )
    deep = consensus_vote(
        t.gaussians, t.trajectory, t.trajectory_gt, t.num_labels, VoteConfig(eps=0.001)
    )
    assert crust.stats["votes_cast"] < deep.stats["votes_cast"]
    assert crust.stats["fraction_voted"] < deep.stats["fraction_voted"]


@pytest.mark.parametrize("method", ["rgc", "flashsplat", "weighted_mean"])
def test_every_rule_counts_the_pairs_that_voted(tiny_task, method):
    """votes_cast is the (pixel, Gaussian) pairs that voted, for every rule (it was None for the
    weighted ones); for rgc it equals the histogram's sum."""
    t = tiny_task
    res = consensus_vote(
        t.gaussians, t.trajectory, t.trajectory_gt, t.num_labels, VoteConfig(method=method)
    )
    assert isinstance(res.stats["votes_cast"], int) and res.stats["votes_cast"] > 0
    if method == "rgc":
        assert res.stats["votes_cast"] == int(res.histogram.sum())


def test_min_votes_below_one_is_refused():
    with pytest.raises(ValueError, match="min_votes=0: must be >= 1"):
        VoteConfig(min_votes=0)
