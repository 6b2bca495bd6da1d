"""The shift that aligns a view's fitted object with its mask (sagonline/score/alignment.py):
found exactly, the nearest of equals, never wrapped round the view; and a planted pose error
in one eval view named by the diagnosis and the run's summary."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sagonline.score.alignment import best_shift, displaced


def _square(h=60, w=80, top=20, left=30, size=20) -> np.ndarray:
    mask = np.zeros((h, w), bool)
    mask[top : top + size, left : left + size] = True
    return mask


@pytest.mark.parametrize(("dy", "dx"), [(0, 0), (3, -5), (-7, 2), (0, 9)])
def test_the_shift_that_aligns_a_displaced_silhouette_is_found(dy, dx):
    truth = _square()
    silhouette = np.roll(np.roll(truth, -dy, 0), -dx, 1)  # drawn (dy, dx) away from the truth
    row = best_shift(truth, silhouette)
    assert (row["shift_dy"], row["shift_dx"]) == (dy, dx)
    assert row["shifted_iou"] == 1.0
    assert row["silhouette_iou"] == (
        1.0
        if (dy, dx) == (0, 0)
        else pytest.approx(
            (20 - abs(dy)) * (20 - abs(dx)) / (800 - (20 - abs(dy)) * (20 - abs(dx))), abs=1e-4
        )
    )


def test_equals_resolve_to_the_nearest_shift_and_nothing_wraps_round():
    """A bar against a longer bar: every shift along it overlaps as much, the nearest (none)
    is taken. A silhouette at the left edge is never matched through the right edge."""
    truth = np.zeros((40, 60), bool)
    truth[18:22, 10:50] = True
    bar = np.zeros_like(truth)
    bar[18:22, 25:35] = True
    assert (best_shift(truth, bar)["shift_dx"], best_shift(truth, bar)["shift_dy"]) == (0, 0)
    edge = np.zeros((40, 60), bool)
    edge[10:20, 0:4] = True  # at the left edge
    far = np.zeros_like(edge)
    far[10:20, 56:60] = True  # at the right edge: 56 px away, beyond the 9 px searched
    row = best_shift(far, edge)
    assert row["shifted_iou"] == 0.0 and row["silhouette_iou"] == 0.0
    assert best_shift(np.zeros_like(edge), edge) == {} == best_shift(edge, np.zeros_like(edge))


def test_displaced_needs_a_shift_and_a_gain():
    row = {"shift_dx": 6, "shift_dy": 0, "silhouette_iou": 0.5, "shifted_iou": 0.9}
    assert displaced(row, 64, 48)
    assert not displaced({**row, "shift_dx": 1}, 64, 48)  # under 2% of the larger side: 1.28
    assert not displaced({**row, "shifted_iou": 0.55}, 64, 48)  # a shift that gains little
    assert not displaced({}, 64, 48)  # no object in the view


def test_a_pose_error_in_one_view_is_named_by_the_diagnosis_and_the_summary(tiny_task):
    """Eval view 1's mask drawn 4 px left of where its camera renders the object (as a wrong
    pose would): that view alone is `displaced`, with the shift that undoes it."""
    from bench.runners.outputs import diagnosis_lines
    from sagonline.pipeline import PipelineSettings, run_scene
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.vote.consensus import VoteConfig

    first, view = tiny_task.eval_views
    moved = np.roll(view.gt, -4, axis=1)
    moved[:, -4:] = 0
    planted = dataclasses.replace(
        tiny_task, eval_views=[first, dataclasses.replace(view, gt=moved)]
    )
    settings = PipelineSettings(progress=False)
    report, _ = run_scene(planted, OracleSegmenter(), VoteConfig(), settings)
    d = report.extra["diagnosis"]
    assert [v["view"] for v in d["displaced"]] == [view.name]
    assert (d["displaced"][0]["shift_dx"], d["displaced"][0]["shift_dy"]) == (-4, 0)
    row = next(r for r in report.views if r["view"] == first.name and r["mode"] == "coarse")
    assert abs(row["shift_dx"]) <= 1 and abs(row["shift_dy"]) <= 1
    lines = diagnosis_lines(d)
    assert any(
        "displaced from its mask in 1 view(s)" in ln and f"{view.name} 4 px" in ln for ln in lines
    )
