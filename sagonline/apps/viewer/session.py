"""The online session behind `sagonline view`, without a browser: clicks on one view -> Stage I's
engine streams the segmenter's masks, votes each as it comes and publishes labels every few
views.

    session = SegmentSession(gaussians, cameras)         # renders every view once
    session.add_click(0, 240, 135)                       # a positive click on view 0
    session.wait()                                        # or watch `on_update` calls arrive
    session.labels                                        # (N,) -1 / 0 background / 1.. objects
    session.export("segment-donut")                      # the layout of `sagonline segment`

A click restarts the engine's stream on the same frames with the prompt grown by one click;
`stop` keeps the labels made so far and `resume` carries on from the next view. When every view
has voted, the labels are those of `segment_scene` on the same prompt: it is the same engine
(`pipeline.stage_one.StageOne`). The browser side is `sagonline.apps.viewer.app`; the timings
are `bench/speed/viewer.py`'s.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sagonline.apps.viewer.clicks import pick_gaussian, view_for_point
from sagonline.apps.viewer.exporting import export_session, segmentation_of
from sagonline.apps.viewer.preparation import Preparation
from sagonline.core.errors import PromptError
from sagonline.core.machine import DEVICE_DEFAULT
from sagonline.pipeline.segment import (
    Segmentation,
    check_click_on_scene,
    segmenter_run_of,
)
from sagonline.pipeline.settings import LabelRenderSettings, RendererSettings
from sagonline.pipeline.stage_one import (
    LabelsUpdated,
    MaskReady,
    PipelineSettings,
    StageOne,
    StageOneConfig,
    ViewVoted,
)
from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import DEFAULT_SEGMENTER, VideoSegmenter, default_segmenter
from sagonline.segment.clicks import ObjectClicks, ParsedPrompt, to_prompt
from sagonline.vote.consensus import VoteConfig


@dataclass
class Progress:
    """Where the current run stands: views segmented and voted (of `total` voting views), its
    state ("idle", "running", "stopped", "done" or "failed") and a line to show."""

    segmented: int = 0
    voted: int = 0
    total: int = 0
    state: str = "idle"
    message: str = "click on the object"
    seconds: float = 0.0


@dataclass
class ClickPoint:
    """Where a click landed: the view, its pixel, and the 3D point it came from (None for a
    click given in pixels)."""

    view: int
    x: float
    y: float
    point: np.ndarray | None = None


class SegmentSession:
    """Clicks -> labels on one scene and its views (see the module docstring).

    gaussians: the scene; cameras: the views in trajectory order; segmenter: the registry's
    `segmenter_kind` built with `segmenter_options` (the classical one by default);
    on_update(labels, progress) is called from the worker thread after the first voted view,
    every `publish_every` voted views, and at the end (labels: (N,) int64); background: the
    renders' colour (the one the scene was fitted on); min_weight: the Export's label renders'
    threshold (`render_labels`)."""

    def __init__(
        self,
        gaussians: Gaussians,
        cameras: list[Camera],
        *,
        segmenter: VideoSegmenter | None = None,
        segmenter_kind: str = DEFAULT_SEGMENTER,
        segmenter_options: list[str] | None = None,
        vote: VoteConfig | None = None,
        backend: str = "auto",
        vote_backend: str = "auto",
        device: str = DEVICE_DEFAULT,
        publish_every: int = 4,
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
        min_weight: float = LABEL_MIN_WEIGHT,
        on_update: Callable[[np.ndarray, Progress], None] | None = None,
    ):
        from sagonline.pipeline.segment import check_cameras_see_scene

        if not cameras:
            raise PromptError("no views to segment")
        if publish_every < 1:
            raise ValueError(f"publish_every {publish_every}: must be at least 1")
        self.segmenter = segmenter or default_segmenter()
        self.segmenter_kind = segmenter_kind  # its name in the registry (labels.json)
        self.segmenter_options = list(segmenter_options or [])
        settings = PipelineSettings(
            RendererSettings(backend, vote_backend),
            LabelRenderSettings(min_weight),
            device=device,
            progress=False,
            background=tuple(background),
        )
        config = StageOneConfig(
            gaussians,
            list(cameras),
            segmenter_run_of(self.segmenter),
            vote or VoteConfig(),
            settings,
            publish_every=publish_every,
            keep_depth=True,
        )
        self.engine = StageOne(config)
        self.gaussians, self.cameras = self.engine.gaussians, self.engine.cameras
        check_cameras_see_scene(self.gaussians, self.cameras)
        self.backend, self.device = backend, settings.device
        self.min_weight = settings.label_render.min_weight
        self.on_update = on_update
        self.objects: list[ObjectClicks] = []
        self.clicks: list[ClickPoint] = []
        self.view: int | None = None  # the prompt view, fixed by the first click
        self.current: str | None = None
        self.labels = np.full(len(gaussians), -1, np.int64)
        self.progress = Progress(total=len(self.engine.voting))
        self._thread: threading.Thread | None = None
        self._lock = threading.RLock()
        self._started = 0.0
        start = time.perf_counter()
        self.frames = self.engine.render()
        self.alphas, self.depths = self.engine.alphas, self.engine.depths
        self.render_seconds = time.perf_counter() - start
        self.on_prepare: Callable[[int, int], None] | None = None
        self.preparation = self._prepare(self.segmenter)

    def _prepare(self, segmenter: VideoSegmenter) -> Preparation:
        """The segmenter's embeddings of every view, in the background from now on
        (`preparation.done` counts them; `on_prepare(done, total)` hears of each)."""

        def said(done: int, total: int) -> None:
            if self.on_prepare is not None:
                self.on_prepare(done, total)

        return Preparation(segmenter, self.frames, lambda: segmenter is self.segmenter, said)

    @property
    def vote(self) -> VoteConfig:
        return self.engine.config.vote

    def configure(
        self,
        *,
        segmenter: VideoSegmenter | None = None,
        kind: str | None = None,
        options: list[str] | None = None,
        vote: VoteConfig | None = None,
    ) -> None:
        """Another segmenter (its registry kind and options) or other vote settings, for the
        next run; the rendered views stay."""
        self.stop()
        changes = {}
        if segmenter is not None:
            self.segmenter, self.segmenter_kind = segmenter, kind or self.segmenter_kind
            self.preparation = self._prepare(segmenter)
            if options is not None:  # else the command line's, which built it too
                self.segmenter_options = list(options)
            changes["segmenter"] = segmenter_run_of(segmenter)
        if vote is not None:
            changes["vote"] = vote
        self.engine.configure(**changes)

    # --- prompts ----------------------------------------------------------------------------

    @property
    def names(self) -> list[str]:
        """The label names: background, then each object that has a click (an object made by
        "New object" and not clicked yet has no label, so it neither numbers the labels nor
        blocks an export)."""
        return ["background", *(o.name for o in self.objects if o.points)]

    def new_object(self, name: str) -> None:
        """Start another object: the next positive clicks are its own."""
        from sagonline.labels.export import object_file_names

        name = name.strip()
        if not name:
            raise PromptError("an object needs a name")
        if name in ("background", *(o.name for o in self.objects)):
            raise PromptError(f"there is already an object named {name!r}")
        object_file_names([*self.names, name])  # a name that cannot have a file: refused now
        with self._lock:
            self.objects = [o for o in self.objects if o.points]  # an unclicked one is replaced
            self.objects.append(ObjectClicks(name))
            self.current = name

    def add_click(
        self, view: int, x: float, y: float, positive: bool = True, point=None, start=True
    ) -> ClickPoint:
        """A click at pixel (x, y) of `view` (its render size); refused (PromptError, nothing
        changed) outside the view, on another view than the session's first click, where
        nothing is drawn (a positive click), or as a negative click with no object yet.
        Restarts the run unless start=False."""
        if not 0 <= view < len(self.cameras):
            raise PromptError(f"view {view} is out of range: there are {len(self.cameras)} views")
        cam = self.cameras[view]
        if not (np.isfinite([x, y]).all() and 0 <= x < cam.width and 0 <= y < cam.height):
            raise PromptError(
                f"({x:g}, {y:g}) is outside view {view} ('{cam.name}'), which renders at "
                f"{cam.width}x{cam.height}"
            )
        if self.view is not None and view != self.view:
            first = self.cameras[self.view].name
            raise PromptError(
                f"this session's clicks are on view {self.view} ('{first}'): the segmenter takes "
                f"its prompt on one view (Clear starts over on another)"
            )
        with self._lock:
            if not positive and (self.current is None or not self.current_object().points):
                raise PromptError("a negative click says what an object is not: click on it first")
            if positive:
                check_click_on_scene(self.alphas[view], cam, view, x, y, self.current or "object")
            if self.current is None:
                self.objects.append(ObjectClicks("object"))
                self.current = "object"
            target = self.current_object()
            (target.points if positive else target.negatives).append((float(x), float(y)))
            self.view = view
            click = ClickPoint(view, float(x), float(y), point)
            self.clicks.append(click)
        if start:
            self.start()
        return click

    def current_object(self) -> ObjectClicks:
        return next(o for o in self.objects if o.name == self.current)

    def click_from_ray(
        self, origin, direction, positive: bool = True, start: bool = True, prefer=None
    ) -> ClickPoint:
        """A click in the 3D view (a ray from the viewer's camera) -> a click on a view: the
        front-most opaque Gaussian the ray passes through, projected into the session's view
        (or, for the first click, into view `prefer` where it sees the point, else the view
        that looks at it most nearly along the ray)."""
        point = pick_gaussian(self.gaussians, origin, direction)
        views = [self.view] if self.view is not None else range(len(self.cameras))
        if self.view is None and prefer is not None:
            # the selected view, where it sees the point; else the best of all views takes it
            with contextlib.suppress(PromptError):
                view_for_point(self.cameras, self.depths, point, direction, [prefer])
                views = [prefer]
        view, x, y = view_for_point(self.cameras, self.depths, point, direction, views)
        return self.add_click(view, x, y, positive, point=point, start=start)

    def clear(self) -> None:
        """Forget every object and click (the labels too); the rendered views stay."""
        self.stop()
        with self._lock:
            self.objects, self.clicks, self.view, self.current = [], [], None, None
            self.engine.set_prompt(type(self.engine.prompt)())
            self.labels = np.full(len(self.gaussians), -1, np.int64)
            self.progress = Progress(total=len(self.engine.voting))

    def parsed(self) -> ParsedPrompt:
        if self.view is None:
            raise PromptError("no click yet: click on the object first")
        return ParsedPrompt(self.view, [o for o in self.objects if o.points], [])

    # --- the run ----------------------------------------------------------------------------

    def start(self) -> None:
        """(Re)start the run for the current prompt on the rendered views."""
        self.stop()
        prompt = to_prompt(self.parsed(), self.view)
        with self._lock:
            self.engine.set_prompt(prompt)
            self.progress = Progress(total=len(self.engine.voting), state="running", message="")
            self._started = time.perf_counter()
        self.resume()

    def resume(self) -> None:
        """Carry on a stopped run from its next view (nothing to do when it is done)."""
        with self._lock:
            state = self.progress.state
            if self.engine.done or self.running or state not in ("running", "stopped"):
                return
            self.progress.state = "running"
            self._thread = threading.Thread(target=self._work, daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 60.0) -> None:
        """Stop after the view in hand; the labels made so far stay."""
        thread = self._thread
        if thread is not None and thread.is_alive():
            self.engine.stop()
            thread.join(timeout)
            if thread.is_alive():
                raise RuntimeError(f"the session's worker did not stop within {timeout:.0f} s")
        self._thread = None

    def wait(self, timeout: float | None = None) -> Progress:
        """Block until the run finishes (or `timeout` seconds); re-raise what failed it."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
        if self.progress.state == "failed":
            raise RuntimeError(self.progress.message)
        return self.progress

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _work(self) -> None:
        p = self.progress
        try:
            for event in self.engine.stream():
                if isinstance(event, MaskReady):
                    p.segmented += 1
                elif isinstance(event, ViewVoted):
                    p.voted = event.voted
                elif isinstance(event, LabelsUpdated):
                    self._publish(event.labels)
            p.state = "done" if self.engine.done else "stopped"
            if not self.engine.done and p.voted:
                self._publish(self.engine.vote_so_far().labels.cpu().numpy())
            elif self.on_update is not None:  # the last word: done (the labels are unchanged)
                self.on_update(self.labels, p)
        except Exception as exc:  # shown in the GUI, re-raised by wait()
            p.state, p.message = "failed", f"{type(exc).__name__}: {exc}"
            if self.on_update is not None:
                self.on_update(self.labels, p)

    def _publish(self, labels: np.ndarray) -> None:
        with self._lock:
            self.labels = np.asarray(labels, np.int64)
            p = self.progress
            p.seconds = time.perf_counter() - self._started
            p.message = f"{p.voted} of {p.total} views voted ({p.seconds:.1f} s)"
        if self.on_update is not None:
            self.on_update(self.labels, self.progress)

    # --- take it with you --------------------------------------------------------------------

    def segmentation(self) -> Segmentation:
        """What the session holds as `segment_scene` gives it (`exporting.segmentation_of`)."""
        return segmentation_of(self)

    def export(
        self,
        out: str | Path,
        *,
        scene: Path | None = None,
        info: dict | None = None,
        overwrite: bool = False,
        record: bool = True,
    ) -> Path:
        """The folder `sagonline segment` writes (`exporting.export_session`)."""
        return export_session(
            self, Path(out), scene=scene, info=info, overwrite=overwrite, record=record
        )
