"""Stage II renders its views on the colour Stage I's frames were rendered on (the scene's
fitted background): the student answers from the renders it learnt from, and the 2D segmenter
of the initial mode sees the frames its prompts were set on."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from sagonline.datasets.generic import PosedMasksDataset
from sagonline.pipeline import PipelineSettings, run_scene
from sagonline.pipeline.scene import record_eval_views
from sagonline.pipeline.scoring import SceneReport
from sagonline.pipeline.stage_two import run_stage_two
from sagonline.pipeline.stages import SegmenterRun
from sagonline.record.recording import Recorder
from sagonline.refine import RefineConfig, RefinementTrainer
from sagonline.segment.novel_view import NovelViewSegmenter
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig
from tests.fixtures import llff_scene, object_mask, write_image

NAMES = [f"IMG_{i:04d}" for i in range(4)]


def white_capture(tmp_path):
    """A capture fitted on white: its task, and Stage I's frames by camera name."""
    cams, scene = llff_scene(tmp_path / "cap", NAMES)
    for cam, name in zip(cams, NAMES, strict=True):
        mask = (object_mask(scene, cam) > 0).astype(np.uint8) * 255
        write_image(tmp_path / "cap" / "masks" / f"{name}.png", mask)
    fit_config = tmp_path / "cap" / "gaussians" / "fit_config.json"
    fit_config.write_text(json.dumps({"background": [1.0, 1.0, 1.0], "seed": 0}))
    task = PosedMasksDataset(tmp_path / "cap", mask_dir="masks").load_scene("cap")
    assert task.background == (1.0, 1.0, 1.0)
    settings = PipelineSettings(progress=False)  # black: the task's colour comes with the task
    segmenter = SegmenterRun(OracleSegmenter())
    _, stage_one = run_scene(task, segmenter, VoteConfig(), settings)
    names = [c.name for c in task.trajectory]
    frames = dict(zip(names, stage_one.frames.value.images, strict=True))
    empty = frames[NAMES[0]].max(-1) == 0
    assert not empty.any() and (frames[NAMES[0]] == 255).any()  # white where nothing is
    return task, settings, segmenter, stage_one, frames


def test_the_student_and_the_segmenter_answer_on_the_renders_stage_one_made(tmp_path, monkeypatch):
    task, settings, segmenter, stage_one, frames = white_capture(tmp_path)

    seen: dict[str, list[np.ndarray]] = {"refined": [], "initial": []}
    predict, answer = RefinementTrainer.predict, NovelViewSegmenter.answer

    def predict_seen(self, frame, coarse, size=None):
        seen["refined"].append(frame)
        return predict(self, frame, coarse, size)

    def answer_seen(self, frame, camera, ground_truth=None):
        seen["initial"].append(frame)
        return answer(self, frame, camera, ground_truth)

    monkeypatch.setattr(RefinementTrainer, "predict", predict_seen)
    monkeypatch.setattr(NovelViewSegmenter, "answer", answer_seen)
    cfg = RefineConfig(max_steps=1, batch_size=2)
    report = SceneReport(scene="cap")
    run_stage_two(task, stage_one, cfg, settings, report, Recorder(None), segmenter=segmenter)
    assert report.refined_miou is not None
    for mode, images in seen.items():
        # the last answers: each eval view alone, in order
        last = images[-len(task.eval_views) :]
        for view, image in zip(task.eval_views, last, strict=True):
            assert np.array_equal(image, frames[view.name]), (mode, view.name)


def test_the_recordings_eval_views_show_the_renders_stage_one_made(tmp_path, monkeypatch):
    """Drawn again, or taken from Stage I's frames where the view's camera is a frame's (then
    not drawn at all): the same pixels."""
    import sagonline.pipeline.scene as scene_module

    task, settings, _, stage_one, frames = white_capture(tmp_path)
    shown = {}

    class Shown:
        enabled = True

        def eval_view(self, scene, i, rgb, *rest, **named):
            shown[task.eval_views[i].name] = rgb

    preds = [view.gt for view in task.eval_views]
    report = SceneReport(scene="cap")
    report.views = [{"iou": 1.0} for _ in preds]
    g, backend = task.gaussians, stage_one.backends.images
    record_eval_views(task, Shown(), preds, report, g, backend, background=task.background)
    assert shown.keys() == frames.keys()
    assert all(np.array_equal(shown[name], frames[name]) for name in shown)
    drawn_again = dict(shown)

    shown.clear()
    calls = []
    eval_render = scene_module.eval_render
    monkeypatch.setattr(scene_module, "eval_render", lambda *a: calls.append(a) or eval_render(*a))
    images = stage_one.frames.value.images
    record_eval_views(task, Shown(), preds, report, g, backend, None, task.background, None, images)
    assert not calls and shown.keys() == drawn_again.keys()
    assert all(np.array_equal(shown[name], drawn_again[name]) for name in shown)
    # a view whose camera no frame has is drawn, at its own pose
    first = task.eval_views[0]
    pose = first.camera.world_to_cam.clone()
    pose[0, 3] += 0.05
    task.eval_views[0] = dataclasses.replace(
        first, camera=dataclasses.replace(first.camera, world_to_cam=pose)
    )
    record_eval_views(task, Shown(), preds, report, g, backend, None, task.background, None, images)
    assert len(calls) == 1 and calls[0][1] is task.eval_views[0].camera
    assert not np.array_equal(shown[first.name], drawn_again[first.name])


def test_the_students_curve_ends_at_the_score_of_its_refined_answers(tmp_path):
    """refine.curve_every: the student scored at the eval views every few steps, from step 0
    (the untrained student answers the coarse render) to where it stopped, whose point is the
    score of the refined answers."""
    task, settings, segmenter, _, _ = white_capture(tmp_path)
    report, stage_one = run_scene(task, segmenter, VoteConfig(), settings)  # scores the coarse
    cfg = RefineConfig(max_steps=3, batch_size=2, crop=32, curve_every=2)
    run_stage_two(task, stage_one, cfg, settings, report, Recorder(None), segmenter=segmenter)
    curve = report.extra["refine"]["curve"]
    assert [p["step"] for p in curve] == [0, 2, 3]
    assert curve[0]["miou"] == pytest.approx(report.miou)  # the coarse render's answer
    assert curve[-1]["miou"] == pytest.approx(report.refined_miou)
    plain = SceneReport(scene="cap")
    cfg = RefineConfig(max_steps=3, batch_size=2, crop=32)
    run_stage_two(task, stage_one, cfg, settings, plain, Recorder(None), segmenter=segmenter)
    assert "curve" not in plain.extra["refine"]
    assert plain.refined_miou == pytest.approx(report.refined_miou)
    spans = SceneReport(scene="cap")  # more averages scored where it stopped, the answers kept
    cfg = RefineConfig(max_steps=3, batch_size=2, crop=32, scored_spans=[2, 5])
    run_stage_two(task, stage_one, cfg, settings, spans, Recorder(None), segmenter=segmenter)
    span_miou = spans.extra["refine"]["span_miou"]
    assert list(span_miou) == ["0", "2", "5", "60"]  # 0: the trained weights; 60: the answers'
    assert spans.refined_miou == pytest.approx(report.refined_miou)
    assert span_miou["60"] == pytest.approx(report.refined_miou)
    assert span_miou["0"] == pytest.approx(curve[-1]["miou_trained"])
