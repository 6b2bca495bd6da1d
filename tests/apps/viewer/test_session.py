"""The viewer's session without a browser: clicks -> the prompt, the incremental vote equal to
`segment_scene`'s batch vote, stop and resume, refusals that change nothing."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
import torch

from sagonline.apps.viewer.session import SegmentSession
from sagonline.pipeline.segment import PromptError, clicks_prompt, segment_scene
from sagonline.scene.trajectory import orbit_around
from sagonline.segment.classical import FlowWatershedSegmenter
from tests.segment.test_clicks import iced_donut


@pytest.fixture(scope="module")
def donut():
    g, parts = iced_donut(60, 28)
    ring, _ = orbit_around(g.means, 8, width=96, height=72)
    return g, parts, ring


def icing_pixel(session: SegmentSession, parts: torch.Tensor, view: int = 0) -> tuple[float, float]:
    """A pixel of view `view` well inside the icing (label 2)."""
    import cv2

    from sagonline.render.api import render_labels

    lab = render_labels(session.gaussians, session.cameras[view], parts, 3, backend="native")
    inner = cv2.erode((lab.numpy() == 2).astype(np.uint8), np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(inner)
    i = np.argsort(xs)[len(xs) // 2]
    return float(xs[i]) + 0.5, float(ys[i]) + 0.5


def test_incremental_vote_equals_the_batch_vote(donut):
    g, parts, ring = donut
    updates = []

    def record(labels, progress):
        updates.append((progress.voted, labels.copy(), progress.state))

    session = SegmentSession(g, ring, backend="native", publish_every=3, on_update=record)
    xy = icing_pixel(session, parts)
    session.add_click(0, *xy)
    assert session.wait(30).state == "done"
    batch = segment_scene(g, ring, clicks_prompt(ring, 0, {"object": [xy]}), backend="native")
    np.testing.assert_array_equal(session.labels, batch.labels)
    assert (session.labels == 1).sum() > 100
    voted = [v for v, _, _ in updates]
    assert voted[0] == 1 and voted[-1] == len(ring) and voted == sorted(voted), voted
    first = (updates[0][1] == 1).sum()  # the labels already visible after one view
    assert first > 0
    assert updates[-1][2] == "done"  # the panel's last word says the run finished
    # a second click on the same object runs again on the same frames
    frames = session.frames
    session.add_click(0, xy[0] + 2, xy[1])
    session.wait(30)
    assert session.frames is frames and session.objects[0].points == [xy, (xy[0] + 2, xy[1])]


class GatedSegmenter(FlowWatershedSegmenter):
    """The classical segmenter that waits at frame `at` until `gate` is set."""

    def __init__(self, at: int):
        super().__init__()
        self.at, self.gate, self.reached = at, threading.Event(), threading.Event()

    def _stream(self, frames, prompt, ground_truth=None):
        for i, mask in super()._stream(frames, prompt, ground_truth):
            if i == self.at:
                self.reached.set()
                self.gate.wait(30)
            yield i, mask


def test_stop_keeps_the_labels_and_resume_finishes_them(donut):
    g, parts, ring = donut
    gated = GatedSegmenter(at=3)
    session = SegmentSession(g, ring, segmenter=gated, backend="native")
    session.add_click(0, *icing_pixel(session, parts))
    assert gated.reached.wait(30)
    stopper = threading.Thread(target=session.stop)
    stopper.start()
    gated.gate.set()  # the view in hand finishes, then the run stops
    stopper.join(30)
    assert session.progress.state == "stopped"
    assert 0 < session.progress.voted < len(ring) and (session.labels == 1).any()
    session.resume()
    assert session.wait(30).state == "done" and session.progress.voted == len(ring)
    ref = SegmentSession(g, ring, backend="native")
    ref.add_click(0, *icing_pixel(ref, parts))
    ref.wait(30)
    np.testing.assert_array_equal(session.labels, ref.labels)


def test_a_ray_through_a_pixel_lands_on_that_pixel(donut):
    g, parts, ring = donut
    session = SegmentSession(g, ring, backend="native")
    x, y = icing_pixel(session, parts, view=2)
    cam = ring[2]
    ray = cam.cam_to_world[:3, :3] @ torch.linalg.inv(cam.K) @ torch.tensor([x, y, 1.0])
    click = session.click_from_ray(cam.center.numpy(), ray.numpy(), start=False)
    assert click.view == 2 and abs(click.x - x) < 4 and abs(click.y - y) < 4, click
    # later clicks go to the session's view, wherever the ray comes from
    other = ring[3]
    x3, y3 = icing_pixel(session, parts, view=3)
    ray3 = other.cam_to_world[:3, :3] @ torch.linalg.inv(other.K) @ torch.tensor([x3, y3, 1.0])
    assert session.click_from_ray(other.center.numpy(), ray3.numpy(), start=False).view == 2


def test_bad_clicks_are_refused_and_change_nothing(donut):
    g, parts, ring = donut
    session = SegmentSession(g, ring, backend="native")
    cases = [
        (lambda: session.add_click(0, 500, 10), "outside view 0"),
        (lambda: session.add_click(0, 1, 1), "no Gaussian is drawn"),  # the black corner
        (
            lambda: session.add_click(0, *icing_pixel(session, parts), positive=False),
            "negative click",
        ),
        (lambda: session.click_from_ray([0, 0, 10], [0, 0, 1]), "hits no Gaussian"),
        (lambda: session.click_from_ray([0, 0, 10], [0, 0, -1]), "outside every view"),
        (lambda: session.new_object("  "), "needs a name"),
    ]
    for action, message in cases[:4] + cases[5:]:
        with pytest.raises(PromptError, match=message):
            action()
        assert session.clicks == [] and session.view is None
    session.add_click(0, *icing_pixel(session, parts), start=False)
    with pytest.raises(PromptError, match="clicks are on view 0"):
        session.add_click(1, *icing_pixel(session, parts, view=1), start=False)
    with pytest.raises(PromptError, match="already an object"):
        session.new_object("object")
    assert len(session.clicks) == 1
    with pytest.raises(PromptError, match="nothing to export"):
        session.export("never-written")


def test_an_export_keeps_the_segmenter_options_and_replays_with_them(donut, tmp_path):
    """labels.json records the segmenter's options (they were written as []) and the label
    renders' threshold, and `segment --prompts` builds the same segmenter from them: the same
    labels, the same label renders."""
    import json

    from sagonline.apps.cli import main
    from sagonline.scene.io import write_ply

    g, parts, ring = donut
    seg = FlowWatershedSegmenter(band_px=2)
    session = SegmentSession(
        g, ring, segmenter=seg, segmenter_options=["band_px=2"], backend="native", min_weight=0.6
    )
    session.add_click(0, *icing_pixel(session, parts))
    session.wait(60)
    write_ply(tmp_path / "donut.ply", g)
    out = session.export(tmp_path / "seg", scene=tmp_path / "donut.ply", info={"orbit": 8})
    record = json.loads((out / "labels.json").read_text())
    assert record["segmenter"] == {"kind": "classical", "options": ["band_px=2"], "weights": []}
    assert record["label_render"] == {"min_weight": 0.6}
    again = tmp_path / "again"
    assert (
        main(
            [
                "segment",
                str(tmp_path / "donut.ply"),
                "--orbit",
                "8",
                "--width",
                "96",
                "--height",
                "72",
                "--backend",
                "native",
                "--prompts",
                str(out / "labels.json"),
                "--out",
                str(again),
                "--no-record",
            ]
        )
        == 0
    )
    assert np.array_equal(np.load(again / "labels.npy"), session.labels)
    assert json.loads((again / "labels.json").read_text())["label_render"] == {"min_weight": 0.6}
    for render in sorted((out / "views").glob("*_labels.png")):
        assert render.read_bytes() == (again / "views" / render.name).read_bytes(), render.name


def test_a_session_on_every_other_view_exports_in_the_full_numbering_and_replays(donut, tmp_path):
    """`sagonline view --every 2`: the session holds views 0, 2, 4, 6; a click on its second
    view is recorded as view 2 (`sagonline cameras`' number) with that view's name, and
    `segment --prompts` segments the same four views to the same labels."""
    import json

    from sagonline.apps.cli import main
    from sagonline.scene.io import write_ply
    from sagonline.scene.views import segmented_views

    g, parts, ring = donut
    session = SegmentSession(
        g, segmented_views(ring, 2), segmenter=FlowWatershedSegmenter(), backend="native"
    )
    session.add_click(1, *icing_pixel(session, parts, view=1))
    session.wait(60)
    write_ply(tmp_path / "donut.ply", g)
    info = {"orbit": 8, "every": 2}
    out = session.export(tmp_path / "seg", scene=tmp_path / "donut.ply", info=info)
    prompt = json.loads((out / "labels.json").read_text())["prompt"]
    assert prompt["view"] == 2 and prompt["view_name"] == ring[2].name
    again = tmp_path / "again"
    replay = ["segment", str(tmp_path / "donut.ply"), "--prompts", str(out / "labels.json")]
    assert main([*replay, "--backend", "native", "--out", str(again), "--no-record"]) == 0
    assert json.loads((again / "labels.json").read_text())["every"] == 2
    assert np.array_equal(np.load(again / "labels.npy"), session.labels)


def test_the_views_are_rendered_on_the_colour_the_scene_was_fitted_on(donut):
    """A scene fitted on white (its fit_config.json says so) is rendered on white in the viewer,
    as `segment` and the evaluation render it: the segmenter sees what the fit saw."""
    g, _, ring = donut
    white = SegmentSession(g, ring, backend="native", background=(1.0, 1.0, 1.0))
    black = SegmentSession(g, ring, backend="native")
    corner = (slice(0, 3), slice(0, 3))
    assert (white.engine.render()[0][corner] == 255).all()
    assert (black.engine.render()[0][corner] == 0).all()


def test_the_panel_turns_the_distance_rule_off_and_refuses_delta_0(donut):
    """The viewer's vote panel, generated from the methods' settings: delta off is no distance
    rule (None), delta 0 is refused by the vote's own check and said in the status line (it
    was taken); min votes 0 likewise; the weighting and the body rule reach the vote; another
    method enables its own settings only, and the other method's stay at their defaults."""
    import socket

    from sagonline.apps.viewer.app import ViewerApp
    from sagonline.core.plugins import VOTE_RULES

    g, _, ring = donut
    session = SegmentSession(g, ring, backend="native")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    app = ViewerApp(session, port=port)
    panel = app.vote_panel
    every = {f.name for plugin in VOTE_RULES for f in dataclasses.fields(plugin.config)}
    assert every | {"body"} == set(panel.inputs)  # one control per setting of every method
    try:
        panel.off["delta"].value = False
        app.change_vote()
        assert session.vote.delta is None
        panel.off["delta"].value = True
        panel.inputs["delta"].value = 0.0
        app.guarded(app.change_vote)
        assert "refused" in app.status.content and "delta" in app.status.content
        assert session.vote.delta == 2.0  # the last accepted setting stays (box on: 2 px)
        panel.inputs["delta"].value = 2.0
        panel.inputs["min_votes"].value = 0
        app.guarded(app.change_vote)
        assert "min_votes" in app.status.content
        panel.inputs["min_votes"].value = 1
        panel.inputs["weighting"].value = "blend"
        panel.inputs["body"].value = True
        app.change_vote()
        assert (session.vote.weighting, session.vote.delta, session.vote.body) == (
            "blend",
            2.0,
            True,
        )
        panel.method.value = "flashsplat"  # rgc's settings disabled and left at their defaults
        panel.inputs["background_slack"].value = 0.25
        app.change_vote()
        assert (session.vote.method, session.vote.background_slack) == ("flashsplat", 0.25)
        assert (session.vote.weighting, session.vote.body) == ("count", True)
        assert panel.inputs["weighting"].disabled and panel.inputs["eps"].disabled
        assert not panel.inputs["background_slack"].disabled
        assert panel.inputs["threshold"].disabled
    finally:
        app.server.stop()


def test_the_first_click_lands_on_the_selected_view_where_it_sees_the_point(donut):
    """After "Look through this view" on another view, the first click belongs to that view
    (it went to whichever view looked most nearly along the ray, and later clicks on the
    selected view were refused)."""
    g, parts, ring = donut
    session = SegmentSession(g, ring, backend="native")
    x, y = icing_pixel(session, parts, view=2)
    cam = ring[2]
    ray = cam.cam_to_world[:3, :3] @ torch.linalg.inv(cam.K) @ torch.tensor([x, y, 1.0])
    click = session.click_from_ray(cam.center.numpy(), ray.numpy(), start=False, prefer=3)
    assert click.view == 3  # view 3 sees the icing point too: the selected view takes it


def test_an_unclicked_new_object_neither_numbers_the_labels_nor_blocks_the_export(donut, tmp_path):
    g, parts, ring = donut
    session = SegmentSession(g, ring, backend="native")
    session.add_click(0, *icing_pixel(session, parts))
    session.wait(60)
    session.new_object("second")
    with pytest.raises(PromptError):  # a click on nothing: "second" stays without a click
        session.add_click(0, 1, 1)
    assert session.names == ["background", "object"]
    out = session.export(tmp_path / "seg", record=False)
    assert (out / "objects" / "object.ply").is_file()
    session.new_object("third")  # the unclicked "second" is replaced, not kept
    assert [o.name for o in session.objects] == ["object", "third"]


def test_labelled_splats_get_a_colour_that_contrasts_with_their_own():
    from sagonline.apps.viewer.colours import highlight_colours, label_tint
    from sagonline.apps.viewer.words import panel_words
    from sagonline.labels.colours import PALETTE

    pink = np.array([0.95, 0.45, 0.6], np.float32)  # the icing: close to label 1's crimson
    rgbs = np.tile(pink, (6, 1))
    labels = np.array([1, 1, 1, 0, 0, -1])
    colours = highlight_colours(rgbs, labels, 2)
    crimson = PALETTE[1] / 255.0
    assert np.linalg.norm(colours[1] - pink) > 2 * np.linalg.norm(crimson - pink)
    out, visible = label_tint(rgbs, labels, 2)
    assert np.allclose(out[:3], colours[1]) and np.allclose(out[3:], pink) and visible.all()
    dimmed, _ = label_tint(rgbs, labels, 2, "dimmed surroundings")
    assert np.allclose(dimmed[3:], 0.25 * pink) and np.allclose(dimmed[:3], colours[1])
    _, alone = label_tint(rgbs, labels, 2, "object alone")
    assert alone.tolist() == [True, True, True, False, False, False]
    _, nothing_yet = label_tint(rgbs, np.full(6, -1), 2, "object alone")
    assert nothing_yet.all()  # nothing labelled yet: the scene stays visible
    said = panel_words("--out seg holds an earlier output; pass --overwrite to replace it")
    assert "--" not in said and "replace an earlier export" in said


class SlowPreparing(FlowWatershedSegmenter):
    """The classical segmenter with a `prepare` that takes `seconds` a view (as a model's
    encoder does) and counts the views it prepared."""

    def __init__(self, seconds: float):
        super().__init__()
        self.seconds, self.prepared = seconds, []

    def prepare(self, frames, progress=None):
        import time

        for i, _ in enumerate(frames):
            time.sleep(self.seconds)
            self.prepared.append(i)
            if progress is not None and progress(i + 1, len(frames)) is False:
                return


def test_the_views_are_prepared_in_the_background_and_a_click_need_not_wait(donut):
    """The session returns once the views are rendered; the segmenter's preparation goes on
    in a thread, counted in `preparation`, heard by `on_prepare`; a click runs meanwhile; a
    segmenter replaced stops its own preparation."""
    g, parts, ring = donut
    slow = SlowPreparing(0.2)
    session = SegmentSession(g, ring, segmenter=slow, backend="native")
    heard = []
    session.on_prepare = lambda done, total: heard.append((done, total))
    assert session.preparation.seconds is None and session.preparation.done < len(ring)
    session.add_click(0, *icing_pixel(session, parts))
    assert session.wait(60).state == "done"
    assert session.preparation.wait(30) and session.preparation.done == len(ring)
    assert heard and heard[-1] == (len(ring), len(ring))
    slower = SlowPreparing(0.3)
    session.configure(segmenter=slower, kind="classical")
    session.configure(segmenter=FlowWatershedSegmenter(), kind="classical")
    import time

    time.sleep(1.0)
    assert len(slower.prepared) <= 2  # stopped after the view in hand


def test_a_malformed_browser_message_is_one_line_not_a_traceback():
    import logging

    from sagonline.apps.viewer.app import OneLineConnectionErrors

    try:
        raise ValueError("MessagePack data is malformed")
    except ValueError:
        import sys

        record = logging.LogRecord(
            "websockets.server",
            logging.ERROR,
            __file__,
            1,
            "connection handler failed",
            (),
            sys.exc_info(),
        )
    assert OneLineConnectionErrors().filter(record) and record.exc_info is None
    assert "malformed message (ValueError: MessagePack data is malformed)" in record.getMessage()
