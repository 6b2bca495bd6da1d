"""The diagnosis of missed pixels (sagonline/score/diagnosis.py) on generated scenes with a planted
cause: a sheet in front of the object in some views (the fit), masks that flicker (the
segmenter and the vote); and the fill rule on a scene with unlabelled interior Gaussians."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from sagonline.pipeline import PipelineSettings, run_scene
from sagonline.scene.gaussians import Gaussians
from sagonline.score.diagnosis import CAUSE_GROUPS
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig, consensus_vote


@pytest.fixture(scope="module")
def scene():
    from sagonline.datasets.synthetic import load_synthetic

    return load_synthetic(
        preset="forward_single",
        layout="forward",
        num_gaussians=4000,
        width=64,
        height=48,
        num_train_views=10,
        num_eval_views=3,
    )[0]


def _group_share(report, view: str, group: str) -> float:
    row = next(r for r in report.views if r["view"] == view and r["mode"] == "coarse")
    missed = row["missed_px"]
    return sum(row[c] for c in CAUSE_GROUPS[group]) / missed if missed else 0.0


def _sheet(task, view: int, fraction: float = 0.25, count: int = 400) -> Gaussians:
    """Opaque grey surfels on a small disc a `fraction` of the way from eval camera `view` to
    the object: in front of the object in that view, far off it in the others."""
    cam = task.eval_views[view].camera
    target = task.gaussians.means[task.gt_labels3d == 1].mean(0)
    eye = cam.center.float()
    centre = eye + fraction * (target - eye)
    axis = (target - eye) / (target - eye).norm()
    a = torch.linalg.cross(axis, torch.tensor([0.0, 0.0, 1.0]))
    a, b = a / a.norm(), torch.linalg.cross(axis, a / a.norm())
    rng = np.random.default_rng(0)
    r = float((target - eye).norm()) * fraction * 0.12
    uv = torch.tensor(rng.uniform(-r, r, (count, 2)), dtype=torch.float32)
    means = centre + uv[:, :1] * a + uv[:, 1:] * b
    q = torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1)
    sh = torch.zeros(count, task.gaussians.sh.shape[1], 3)
    return Gaussians(
        means=means,
        quats=q,
        scales=torch.full((count, 2), r / 6),
        opacities=torch.full((count,), 0.95),
        sh=sh,
    )


def test_a_sheet_in_front_of_the_object_is_the_fits_fault(scene):
    """The truth stays the clean object's (as a photograph's mask would); the sheet is a fit's
    floater that covers the object in eval view 0: its misses are the fit's."""
    sheet = _sheet(scene, 0)
    g = scene.gaussians
    fitted = Gaussians(
        *(
            torch.cat([getattr(g, f.name), getattr(sheet, f.name)])
            for f in dataclasses.fields(Gaussians)
            if f.name != "normals"
        ),
    )
    planted = dataclasses.replace(scene, gaussians=fitted)
    planted.gt_labels3d = None
    clean, _ = run_scene(scene, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False))
    report, _ = run_scene(
        planted, OracleSegmenter(), VoteConfig(), PipelineSettings(progress=False)
    )
    view = scene.eval_views[0].name
    iou = {r["view"]: r["iou"] for r in report.views}
    assert iou[view] < {r["view"]: r["iou"] for r in clean.views}[view] - 0.05  # it hurts
    assert _group_share(report, view, "fit") > 0.8
    row = next(r for r in report.views if r["view"] == view)
    assert row["fit_occluded"] > row["missed_px"] / 2
    # what the segmenter could not see, whatever the labels: the sheet hides a part of the
    # object in view 0 only, and nothing of it in the clean fit
    assert row["hidden_px"] >= row["fit_occluded"] > 0
    others = [r for r in report.views if r["view"] != view and r["mode"] == "coarse"]
    assert all(r["hidden_px"] < 0.02 * r["object_px"] for r in others)
    assert all(r["hidden_px"] < 0.02 * r["object_px"] for r in clean.views if r["mode"] == "coarse")
    d = report.extra["diagnosis"]
    assert d["hidden_views"] == 1
    total = sum(r["object_px"] for r in report.views if r["mode"] == "coarse")
    assert d["hidden"] == pytest.approx(
        sum(r["hidden_px"] for r in report.views if r["mode"] == "coarse") / total
    )


def test_flickering_masks_are_the_segmenters_and_the_votes_fault(scene):
    flicker = OracleSegmenter(flicker=0.45, seed=3)
    report, _ = run_scene(scene, flicker, VoteConfig(), PipelineSettings(progress=False))
    missed = sum(r["missed_px"] for r in report.views)
    assert missed > 0
    d = report.extra["diagnosis"]
    assert d["counterfactual"] == "truth's masks"
    assert d["share_segmenter"] + d["share_vote"] > 0.8 and d["share_fit"] < 0.2


def test_the_fill_rule_labels_unlabelled_interior_gaussians(scene):
    """Holes in a labelled surface (a fifth of the object's Gaussians left unlabelled, inside
    the labelled patch) take their neighbours' label; a floater far from every labelled
    Gaussian stays unlabelled; labels the vote gave are never changed."""
    from sagonline.vote.fill import fill_from_neighbours

    g = scene.gaussians
    truth = scene.gt_labels3d
    rng = np.random.default_rng(2)
    holes = torch.from_numpy(rng.random(len(g)) < 0.2) & (truth == 1)
    means = torch.cat([g.means, g.means[truth == 1].mean(0, keepdim=True) + 50.0])
    labels = torch.cat([torch.where(holes, -1, truth), torch.tensor([-1])])
    labelled = labels >= 0
    filled_labels, filled = fill_from_neighbours(means, labels, 8)
    assert (filled_labels[:-1][holes] == 1).float().mean() > 0.9
    assert filled[:-1][holes].float().mean() > 0.9 and not filled[-1]
    assert torch.equal(filled_labels[labelled], labels[labelled])

    sparse = VoteConfig(stride=5)  # 2 of 10 views vote: many Gaussians go unseen
    off = consensus_vote(g, scene.trajectory, scene.trajectory_gt, 2, sparse, backend="native")
    on = consensus_vote(
        g,
        scene.trajectory,
        scene.trajectory_gt,
        2,
        dataclasses.replace(sparse, fill=8),
        backend="native",
    )
    kept = off.labels >= 0
    assert on.stats["fraction_filled"] > 0 and (on.labels >= 0).sum() > kept.sum()
    assert torch.equal(on.labels[kept], off.labels[kept])  # votes kept


def test_fill_is_refused_nowhere_and_off_by_default():
    assert VoteConfig().fill == 0
    VoteConfig(method="flashsplat", fill=4)  # every method reads it
    with pytest.raises(ValueError, match="consensus.fill=-1"):
        VoteConfig(fill=-1)


def _outside_rows(task, gaussians, labels):
    """Label renders of `labels` (N,) scored per Gaussian against the task's clean truth."""
    from sagonline.render.api import render_labels
    from sagonline.score.diagnosis import GaussianCauses, OutsideTally, diagnose_view

    hist = torch.nn.functional.one_hot(labels, task.num_labels).float() * 5
    causes = GaussianCauses(labels, labels >= 0, hist.sum(1), labels < -1, None, hist)
    tally, extra = OutsideTally(), 0
    for i, view in enumerate(task.eval_views):
        pred = render_labels(gaussians, view.camera, labels, task.num_labels).numpy()
        counts, _ = diagnose_view(
            gaussians, view.camera, view.gt, pred, causes, outside=tally, voted=i == 0
        )
        extra += counts["extra_px"]
    rows = tally.rows(gaussians, causes)
    assert sum(r["extra_px"] for r in rows) <= extra  # each extra pixel told once
    return rows


def test_floaters_labelled_as_the_object_are_named_per_gaussian(scene):
    """A sheet of surfels half way between eval camera 0 and the object, labelled as the
    object: the Gaussians shown outside the silhouette are the sheet's, in front of the
    object, floating apart from its body, and seen in views that did not vote."""
    from sagonline.score.diagnosis import outside_summary

    sheet = _sheet(scene, 0, fraction=0.5)
    g = scene.gaussians
    fitted = Gaussians(
        *(
            torch.cat([getattr(g, f.name), getattr(sheet, f.name)])
            for f in dataclasses.fields(Gaussians)
            if f.name != "normals"
        ),
    )
    labels = torch.cat([scene.gt_labels3d, torch.ones(len(sheet), dtype=torch.long)])
    rows = _outside_rows(scene, fitted, labels)
    assert rows and all(r["gaussian"] >= len(g) for r in rows)  # the sheet's, and only
    assert [r["extra_px"] for r in rows] == sorted((r["extra_px"] for r in rows), reverse=True)
    summary = outside_summary(rows, sum(r["extra_px"] for r in rows))
    assert summary["share_in_front"] > 0.8 and summary["share_floating"] > 0.9
    assert summary["share_not_voting"] > 0.5 and summary["share_confident"] == 1.0


def test_background_beside_the_object_labelled_as_it_is_attached_and_beside(scene):
    """Background Gaussians touching the object's body (centres nearer than their extents),
    labelled as the object: beside it (at its depths, outside its silhouette) and part of its
    body, not floating."""
    from sagonline.score.diagnosis import outside_summary

    g, truth = scene.gaussians, scene.gt_labels3d
    near = torch.cdist(g.means, g.means[truth == 1]).min(1).values
    rim = (truth == 0) & (near < g.scales.amax(1))  # nearer than its own extent: touching
    assert rim.sum() > 10
    rows = _outside_rows(scene, g, torch.where(rim, 1, truth))
    assert rows and all(bool(rim[r["gaussian"]]) for r in rows)
    summary = outside_summary(rows, sum(r["extra_px"] for r in rows))
    assert summary["share_beside"] > 0.5 and summary["share_floating"] < 0.2


def test_the_body_rule_unlabels_floaters_and_keeps_the_object(scene):
    """`consensus.body`: the sheet labelled as the object floats apart from its body and is
    left unlabelled; every Gaussian of the object keeps its label, and the background too."""
    from sagonline.vote.body import keep_bodies

    sheet = _sheet(scene, 0, fraction=0.5)
    g = scene.gaussians
    means = torch.cat([g.means, sheet.means])
    reach = torch.cat([g.scales.amax(1), sheet.scales.amax(1)]).numpy()
    labels = torch.cat([scene.gt_labels3d, torch.ones(len(sheet), dtype=torch.long)])
    kept, dropped = keep_bodies(means, reach, labels)
    assert bool(dropped[len(g) :].all()) and not bool(dropped[: len(g)].any())
    assert torch.equal(kept[: len(g)], scene.gt_labels3d) and bool((kept[len(g) :] == -1).all())


def test_the_body_rule_is_off_by_default_and_runs_through_the_pipeline(scene):
    assert VoteConfig().body is False
    report, out = run_scene(
        scene, OracleSegmenter(), VoteConfig(body=True), PipelineSettings(progress=False)
    )
    assert report.miou is not None and "fraction_off_body" in out.vote.value.stats


def test_a_recording_renders_each_eval_views_colours_once_and_moves_no_diagnosis(
    scene, monkeypatch
):
    """On the compiled kernel the diagnosis reads each eval view's surface from its label
    render's walk, unshaded: with a recording, `run_scene` renders each eval view's colours once
    (no ids) for it; without one, it shades nothing; neither draws the surface again. The
    counts, the shares and the cause images are the same both ways, and those of a diagnosis
    that draws each view's surface itself."""
    from sagonline.pipeline import scene as scene_module
    from sagonline.pipeline.diagnose import SceneDiagnosis
    from sagonline.pipeline.graph import StageCache
    from sagonline.pipeline.scoring import SceneReport
    from sagonline.pipeline.stages import SegmenterRun
    from sagonline.render import native
    from sagonline.render.api import render, to_uint8

    calls, shown, drawn = [], {}, []

    def counted(g, camera, **options):
        calls.append((camera.name, bool(options.get("return_ids"))))
        return render(g, camera, **options)

    surface = native.surface_native
    monkeypatch.setattr(
        native, "surface_native", lambda g, cam: drawn.append(cam.name) or surface(g, cam)
    )

    class Shown:
        enabled = True

        def eval_view(self, name, i, rgb, pred, gt, *, diagnosis, **named):
            shown[i] = (rgb, pred, diagnosis)

        def __getattr__(self, name):
            return lambda *args, **named: None

    monkeypatch.setattr(scene_module, "render", counted)
    settings, segmenter = PipelineSettings(progress=False), OracleSegmenter(flicker=0.3, seed=1)
    report, stage_one = run_scene(scene, segmenter, VoteConfig(), settings, recorder=Shown())
    assert calls == [(view.camera.name, False) for view in scene.eval_views]
    assert sum(r["missed_px"] for r in report.views if r["mode"] == "coarse") > 0
    calls.clear()
    unrecorded, _ = run_scene(scene, segmenter, VoteConfig(), settings)
    assert calls == []  # nothing shaded
    assert unrecorded.views == report.views
    assert unrecorded.extra["diagnosis"] == report.extra["diagnosis"]
    assert drawn == []  # each surface the label render's
    names = [view.camera.name for view in scene.eval_views]
    monkeypatch.setattr(scene_module, "SURFACES_KEPT_BYTES", 0)  # none kept: each drawn again
    bounded, _ = run_scene(scene, segmenter, VoteConfig(), settings)
    assert drawn == names and bounded.views == report.views
    drawn.clear()

    again = SceneReport(scene=scene.name)
    again.views = [dict(r) for r in report.views]
    g, cache = scene.gaussians, StageCache(None)
    diagnosis = SceneDiagnosis(
        scene, g, stage_one, SegmenterRun(segmenter), VoteConfig(), settings, again, cache
    )
    for i, view in enumerate(scene.eval_views):
        rgb, pred, causes = shown[i]
        assert np.array_equal(rgb, to_uint8(render(g, view.camera, backend="auto").rgb))
        assert np.array_equal(diagnosis.view(view, pred), causes)  # drawn by the diagnosis
    diagnosis.finish()
    assert drawn == names
    assert again.views == report.views
    assert again.extra["diagnosis"] == report.extra["diagnosis"]


def test_the_truths_vote_takes_the_runs_frames_and_ignores_frames_of_other_inputs(
    scene, monkeypatch
):
    """Without a cache, the diagnosis's counterfactual (the truth's masks voting on the same
    views) votes on the frames the run rendered: each trajectory view is rendered once. Frames
    handed over under another key are not taken."""
    from sagonline.pipeline import stage_one as stage_one_module
    from sagonline.pipeline.graph import Output
    from sagonline.pipeline.stage_one import StageOne, StageOneConfig
    from sagonline.pipeline.stages import SegmenterRun

    rendered = []
    real = stage_one_module.render

    def counted(g, camera, **options):
        rendered.append(camera.name)
        return real(g, camera, **options)

    monkeypatch.setattr(stage_one_module, "render", counted)
    flicker = OracleSegmenter(flicker=0.45, seed=3)
    report, stage_one = run_scene(scene, flicker, VoteConfig(), PipelineSettings(progress=False))
    assert report.extra["diagnosis"]["counterfactual"] == "truth's masks"
    assert rendered == [c.name for c in scene.trajectory]  # the run's; none for the truth

    rendered.clear()
    other = Output("another key", stage_one.frames.value)
    config = StageOneConfig(
        scene.gaussians, scene.trajectory, SegmenterRun(OracleSegmenter()), rendered=other
    )
    StageOne(config).render()
    assert len(rendered) == len(scene.trajectory)
