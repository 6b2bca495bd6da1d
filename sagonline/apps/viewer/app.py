"""The browser side of `sagonline view`, on viser: the scene as splats, the views as frustums,
clicks in the 3D view as prompts, the labels recoloured as they form, the exports.

    click                 a positive click on the object (on the session's view)
    shift + click         a negative click (what the object is not)
    a frustum             selects that view: its render, index and name in the panel

Everything it does goes through `SegmentSession` (sagonline.apps.viewer.session); this module only
draws and forwards.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np
import torch

from sagonline.apps.viewer.colours import SHOW, label_tint, splat_arrays
from sagonline.apps.viewer.session import Progress, SegmentSession
from sagonline.apps.viewer.vote_panel import VotePanel
from sagonline.apps.viewer.words import (
    CLICK_EXTENTS,
    click_extent_of,
    panel_words,
    segmenter_words,
)
from sagonline.scene.gaussians import rotmat_to_quat
from sagonline.segment.base import DEFAULT_SEGMENTER

SELECTED, OTHER = (255, 200, 0), (120, 120, 120)  # frustum colours: the selected view, the rest


RECOLOUR_SECONDS = 1.0  # the least time between two recolours sent while a run votes


def draw_clicks(frame: np.ndarray, view: int | None, objects) -> np.ndarray:
    """The view's render with its clicks: a green ring per positive, a red cross per negative."""
    import cv2

    image = frame.copy()
    if view is None:
        return image
    for obj in objects:
        for x, y in obj.points:
            cv2.circle(image, (int(x), int(y)), 6, (0, 255, 0), 2, cv2.LINE_AA)
        for x, y in obj.negatives:
            p = (int(x), int(y))
            cv2.drawMarker(image, p, (255, 0, 0), cv2.MARKER_TILTED_CROSS, 12, 2, cv2.LINE_AA)
    return image


class OneLineConnectionErrors(logging.Filter):
    """A browser connection that sends what is not a viser message (junk on the websocket)
    fails in the websockets library, which logs a traceback: said as one line instead."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            record.msg = (
                "viewer: closed a connection that sent a malformed message "
                f"({type(exc).__name__}: {exc})"
            )
            record.args, record.exc_info, record.exc_text = (), None, None
        return True


class ViewerApp:
    """One viser server around one session. scene: the file (labels.json records it); out:
    the default export folder; make_segmenter(kind) -> a segmenter of the registry (the CLI's
    builder, checkpoint included)."""

    def __init__(
        self,
        session: SegmentSession,
        *,
        scene: Path | None = None,
        info: dict | None = None,
        out: str = "segment-view",
        host: str = "127.0.0.1",
        port: int = 8080,
        make_segmenter=None,
        segmenters: tuple[str, ...] = (DEFAULT_SEGMENTER,),
    ):
        import viser

        for name in ("websockets.server", "websockets.asyncio.server"):
            logging.getLogger(name).addFilter(OneLineConnectionErrors())
        self.session, self.scene, self.info = session, scene, dict(info or {})
        self.every = int(self.info.get("every") or 1)  # the session's views: every N-th
        self.make_segmenter = make_segmenter
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host = host
        self.selected = session.view or 0
        self.updates = 0  # recolours sent (the browser test waits on it)
        self.hidden = False  # whether the splats' opacities hide the surroundings now
        self.drawn = None  # (labels, show, number of labels) the splats were last coloured by
        self.last_draw = 0.0  # when (perf_counter) they were
        self.click_markers: list = []
        self._draw_lock = threading.Lock()
        self.arrays = splat_arrays(session.gaussians)
        self._draw_scene()
        self._build_gui(out, segmenters)
        session.on_update = self.on_update
        session.on_prepare = self.on_prepare
        self.server.scene.on_click()(lambda event: self.on_scene_click(event, positive=True))
        self.server.scene.on_click(modifier="shift")(
            lambda event: self.on_scene_click(event, positive=False)
        )

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.server.get_port()}"

    # --- the scene ----------------------------------------------------------------------------

    def _draw_scene(self) -> None:
        a, s = self.arrays, self.session
        self.splats = self.server.scene.add_gaussian_splats(
            "/scene/splats", a["centers"], a["covariances"], a["rgbs"], a["opacities"]
        )
        centres = np.stack([c.center.cpu().numpy() for c in s.cameras])
        middle = np.median(a["centers"], axis=0)
        size = float(np.median(np.linalg.norm(centres - middle, axis=1)))
        self.click_radius = 0.01 * size
        first = s.cameras[0]
        back = middle + 1.6 * (first.center.cpu().numpy() - middle)  # the first view, stepped back
        self.server.initial_camera.position = tuple(back.tolist())
        self.server.initial_camera.look_at = tuple(middle.tolist())
        self.server.initial_camera.up = tuple((-first.cam_to_world[:3, 1]).cpu().numpy().tolist())
        rotations = torch.stack([c.cam_to_world[:3, :3].cpu() for c in s.cameras])
        wxyz = rotmat_to_quat(rotations).numpy()
        self.frustums: list = []
        for i, cam in enumerate(s.cameras):
            fy = float(cam.K[1, 1])
            frustum = self.server.scene.add_camera_frustum(
                f"/cameras/{i:04d}",
                fov=2 * np.arctan(cam.height / (2 * fy)),
                aspect=cam.width / cam.height,
                scale=0.04 * size,
                thickness=0.002 * size,
                wxyz=wxyz[i],
                position=centres[i],
                color=OTHER,
            )
            frustum.on_click(lambda _event, view=i: self.select_view(view))
            self.frustums.append(frustum)
        self.frustums[self.selected].color = SELECTED

    # --- the panel ----------------------------------------------------------------------------

    def _build_gui(self, out: str, segmenters: tuple[str, ...]) -> None:
        gui, s = self.server.gui, self.session
        gui.add_markdown(
            "**Click** the object in the 3D view: a positive click. **Shift+click**: a negative "
            "one. A frustum shows its view here. The labels spread view by view."
        )
        self.status = gui.add_markdown("click on the object")
        self.bar = gui.add_progress_bar(0.0)
        with gui.add_folder("View"):
            self.view_choice = gui.add_dropdown(
                "view",
                [self.view_label(i) for i in range(len(s.cameras))],
                initial_value=self.view_label(self.selected),
            )
            self.view_choice.on_update(lambda _: self.select_view(self.view_choice_index()))
            self.view_image = gui.add_image(
                s.frames[self.selected], label=self.view_label(self.selected)
            )
            gui.add_button("Look through this view").on_click(self.look_through)
            self.show = gui.add_dropdown("show", SHOW, initial_value=SHOW[0])
            self.show.on_update(lambda _: self.on_update(s.labels, s.progress))
        with gui.add_folder("Objects"):
            self.object_name = gui.add_text("name", initial_value="object")
            gui.add_button("New object").on_click(lambda _: self.guarded(self.new_object))
            self.stop_button = gui.add_button("Stop")
            self.stop_button.on_click(lambda _: self.guarded(s.stop))
            gui.add_button("Resume").on_click(lambda _: self.guarded(s.resume))
            gui.add_button("Clear").on_click(lambda _: self.guarded(self.clear))
        with gui.add_folder("Segmenter and vote"):
            self.segmenter_choice = gui.add_dropdown(
                "segmenter", list(segmenters), initial_value=s.segmenter_kind
            )
            self.segmenter_choice.on_update(lambda _: self.guarded(self.change_segmenter))
            self.model_status = gui.add_markdown(segmenter_words(s))
            self.click_extent = gui.add_dropdown(
                "a click selects", CLICK_EXTENTS, initial_value=click_extent_of(s.segmenter)
            )
            self.click_extent.disabled = not hasattr(s.segmenter, "click_extent")
            self.click_extent.on_update(lambda _: self.guarded(self.change_segmenter))
            self.vote_panel = VotePanel(gui, s.vote, lambda: self.guarded(self.change_vote))
        with gui.add_folder("Export"):
            self.out_text = gui.add_text("folder", initial_value=out)
            self.overwrite = gui.add_checkbox("replace an earlier export", initial_value=False)
            self.export_button = gui.add_button("Export objects, labels, recording")
            self.export_status = gui.add_markdown("")  # under the button, where the eye is
            self.export_button.on_click(lambda _: self.guarded(self.export, self.export_status))

    def view_label(self, i: int) -> str:
        """'8: IMG_0008': the session's view i by its number in `sagonline cameras` (with
        --every N the session holds views 0, N, 2N, ...) and its name."""
        return f"{i * self.every}: {self.session.cameras[i].name}"

    def view_choice_index(self) -> int:
        return int(str(self.view_choice.value).split(":", 1)[0]) // self.every

    def select_view(self, view: int) -> None:
        """Show `view`'s render (with the session's clicks when it is their view)."""
        s = self.session
        self.frustums[self.selected].color = OTHER
        self.frustums[view].color = SELECTED  # the selected view, marked in 3D
        self.selected = view
        label = self.view_label(view)
        if self.view_choice.value != label:
            self.view_choice.value = label
        self.view_image.image = draw_clicks(
            s.frames[view], s.view if s.view == view else None, s.objects
        )
        self.view_image.label = label

    def look_through(self, _event=None) -> None:
        """Move every browser's camera to the selected view (a click then lands on it)."""
        cam = self.session.cameras[self.selected]
        wxyz = rotmat_to_quat(cam.cam_to_world[None, :3, :3].cpu())[0].numpy()
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.wxyz = wxyz
                client.camera.position = cam.center.cpu().numpy()
                client.camera.fov = float(2 * np.arctan(cam.height / (2 * float(cam.K[1, 1]))))

    # --- what the buttons and clicks do ----------------------------------------------------

    def guarded(self, action, status=None) -> None:
        """Run a GUI action; a refusal (bad click, name, setting) becomes the status line (or
        `status`, a line beside the control that was used)."""
        from sagonline.core.outputs import OutputError

        try:
            action()
        except (ValueError, RuntimeError, OutputError) as exc:
            (status or self.status).content = f"**refused:** {panel_words(str(exc))}"

    def on_scene_click(self, event, positive: bool) -> None:
        if event.ray_origin is None or event.ray_direction is None:
            return
        self.guarded(lambda: self.click(event.ray_origin, event.ray_direction, positive))

    def click(self, origin, direction, positive: bool) -> None:
        # the first click lands on the selected view where that view sees the point
        click = self.session.click_from_ray(origin, direction, positive, prefer=self.selected)
        n = len(self.session.clicks)
        marker = self.server.scene.add_icosphere(
            f"/clicks/{n:03d}",
            radius=self.click_radius,
            position=click.point,
            color=(0, 220, 0) if positive else (230, 0, 0),
        )
        self.click_markers.append(marker)
        self.status.content = (
            f"{'positive' if positive else 'negative'} click on {self.session.current!r}: "
            f"view {self.view_label(click.view)} at ({click.x:.0f}, {click.y:.0f})"
        )
        self.select_view(click.view)

    def new_object(self) -> None:
        self.session.new_object(self.object_name.value)
        self.status.content = f"new object {self.object_name.value!r}: click on it"

    def clear(self) -> None:
        self.session.clear()
        for marker in self.click_markers:
            marker.remove()
        self.click_markers = []
        self.on_update(self.session.labels, self.session.progress)

    def change_segmenter(self) -> None:
        kind = str(self.segmenter_choice.value)
        if self.make_segmenter is None:
            raise ValueError("this viewer was started with one segmenter")
        from dataclasses import fields

        from sagonline.core.plugins import SEGMENTERS

        extent = ()
        if "click_extent" in {f.name for f in fields(SEGMENTERS[kind].config)}:
            extent = (f"click_extent={self.click_extent.value}",)
        segmenter = self.make_segmenter(kind, extent)
        kept = [o for o in self.session.segmenter_options if not o.startswith("click_extent=")]
        options = [*kept, *extent] if extent else None
        self.session.configure(segmenter=segmenter, kind=kind, options=options)
        self.click_extent.disabled = not hasattr(segmenter, "click_extent")
        self.model_status.content = segmenter_words(self.session)
        self.restart()

    def on_prepare(self, done: int, total: int) -> None:
        """A model's embeddings, view by view, in the panel."""
        self.model_status.content = segmenter_words(self.session)

    def change_vote(self) -> None:
        """The panel's vote settings (`VotePanel.config`; a value out of range is refused by
        VoteConfig and shown), then a new run where there are clicks."""
        self.session.configure(vote=self.vote_panel.config())
        self.restart()

    def restart(self) -> None:
        if self.session.clicks:
            self.session.start()

    def export(self) -> Path:
        out = Path(self.out_text.value)
        self.export_status.content = f"exporting to {out} ..."
        written = self.session.export(
            out, scene=self.scene, info=self.info, overwrite=self.overwrite.value
        )
        self.export_status.content = (
            f"exported to {written} (labels.json: `sagonline segment --prompts`)"
        )
        return written

    # --- from the session's worker ----------------------------------------------------------

    def on_update(self, labels: np.ndarray, progress: Progress) -> None:
        """Recolour the splats by the current labels; move the progress line."""
        with self._draw_lock:
            a = self.arrays
            show = str(self.show.value)
            drawn = (labels.copy(), show, len(self.session.names))
            changed = self.drawn is None or not (
                np.array_equal(drawn[0], self.drawn[0]) and drawn[1:] == self.drawn[1:]
            )
            # the splats (the whole buffer) go to the browser again only when their colours
            # change, and while voting at most every RECOLOUR_SECONDS after the first labels:
            # each send costs a software-WebGL browser a redraw that delays the next click
            settled = progress.state != "running" or progress.voted <= 1
            due = time.perf_counter() - self.last_draw >= RECOLOUR_SECONDS
            if changed and (settled or due):
                rgbs, visible = label_tint(a["rgbs"], labels, len(self.session.names), show)
                self.splats.rgbs = rgbs
                if not visible.all() or self.hidden:
                    self.splats.opacities = a["opacities"] * visible[:, None]
                    self.hidden = not visible.all()
                self.drawn = drawn
                self.last_draw = time.perf_counter()
            self.bar.value = 100.0 * progress.voted / max(len(self.session.cameras), 1)
            counts = ", ".join(
                f"{name} {int((labels == k).sum())}"
                for k, name in enumerate(self.session.names)
                if k
            )
            line = progress.message or progress.state
            self.status.content = f"{progress.state}: {line}" + (f" ({counts})" if counts else "")
            self.updates += 1
            self.last_update = time.perf_counter()
