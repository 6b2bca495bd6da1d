"""The online loop behind `sagonline view`, without a browser: clicks on one view -> the
segmenter's masks, one by one -> each voted into the running histogram -> labels every few views.

    session = SegmentSession(gaussians, cameras)         # renders every view once
    session.add_click(0, 240, 135)                       # a positive click on view 0
    session.wait()                                        # or watch `on_update` calls arrive
    session.labels                                        # (N,) -1 / 0 background / 1.. objects
    session.export("segment-donut")                      # the layout of `sagonline segment`

A click restarts the run on the same frames with the prompt grown by one click; `stop` keeps
the labels made so far and `resume` carries on from the next view. When every view has voted,
the labels are those of `segment_scene` on the same prompt (the same masks, the same vote).
The browser side is `sagonline.apps.viewer.app`; the timings are `bench/bench_viewer.py`'s.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from sagonline.apps.viewer.clicks import pick_gaussian, view_for_point
from sagonline.pipeline.segment import (
    PromptError,
    Segmentation,
    check_cameras_see_scene,
    check_click_on_scene,
    check_objects_were_found,
    write_segment_folder,
)
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.clicks import ObjectClicks, ParsedPrompt, to_prompt
from sagonline.vote.consensus import VoteAccumulator, VoteConfig, VoteResult, select_frames


@dataclass
class Progress:
    """Where the current run stands: views segmented and voted (of `total`), its state
    ("idle", "running", "stopped", "done" or "failed") and a line to show."""

    segmented: int = 0
    voted: int = 0
    total: int = 0
    state: str = "idle"
    message: str = "click on the object"
    seconds: float = 0.0


@dataclass
class Run:
    """One prompt's pass over the views: the segmenter's stream, the running histogram, the
    masks made so far (None until made)."""

    stream: Iterator[tuple[int, np.ndarray]]
    votes: VoteAccumulator
    voting: set[int]
    masks: list[np.ndarray | None]
    started: float = field(default_factory=time.perf_counter)
    finished: bool = False


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
    `segmenter_kind` built (the classical one by default); on_update(labels, progress)
    is called from the worker thread after the first voted view, every `recolour_every` voted
    views, and at the end (labels: (N,) int64)."""

    def __init__(
        self,
        gaussians: Gaussians,
        cameras: list[Camera],
        *,
        segmenter: VideoSegmenter | None = None,
        segmenter_kind: str = "classical",
        vote: VoteConfig | None = None,
        backend: str = "auto",
        device: str = "cpu",
        recolour_every: int = 4,
        on_update: Callable[[np.ndarray, Progress], None] | None = None,
    ):
        from sagonline.segment.classical import FlowWatershedSegmenter

        if not cameras:
            raise PromptError("no views to segment")
        if recolour_every < 1:
            raise ValueError(f"recolour_every {recolour_every}: must be at least 1")
        self.gaussians = gaussians.to(device)
        self.cameras = [c.to(device) for c in cameras]
        check_cameras_see_scene(self.gaussians, self.cameras)
        self.segmenter = segmenter or FlowWatershedSegmenter()
        self.segmenter_kind = segmenter_kind  # its name in the registry (labels.json)
        self.vote = vote or VoteConfig()
        self.backend, self.device = backend, device
        self.recolour_every, self.on_update = recolour_every, on_update
        self.objects: list[ObjectClicks] = []
        self.clicks: list[ClickPoint] = []
        self.view: int | None = None  # the prompt view, fixed by the first click
        self.current: str | None = None
        self.labels = np.full(len(gaussians), -1, np.int64)
        self.progress = Progress(total=len(cameras))
        self._run: Run | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.RLock()
        self.frames, self.alphas, self.depths = self._render_views()

    # --- the views, rendered once ---------------------------------------------------------

    def _render_views(self) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
        """RGB (H, W, 3) uint8, opacity (H, W) and surface depth (H, W) of every view."""
        from sagonline.render.api import render, to_uint8

        start = time.perf_counter()
        frames, alphas, depths = [], [], []
        with torch.no_grad():
            for cam in self.cameras:
                out = render(self.gaussians, cam, backend=self.backend)
                alpha = out.alpha.detach().float().cpu().numpy()
                depth = out.depth.detach().float().cpu().numpy() / np.maximum(alpha, 1e-6)
                frames.append(np.ascontiguousarray(to_uint8(out.rgb)))
                alphas.append(alpha)
                depths.append(np.where(alpha > 0.5, depth, np.inf))
        self.render_seconds = time.perf_counter() - start
        return frames, alphas, depths

    # --- prompts ----------------------------------------------------------------------------

    @property
    def names(self) -> list[str]:
        return ["background", *(o.name for o in self.objects)]

    def new_object(self, name: str) -> None:
        """Start another object: the next positive clicks are its own."""
        from sagonline.labels.export import object_file_names

        name = name.strip()
        if not name:
            raise PromptError("an object needs a name")
        if name in self.names:
            raise PromptError(f"there is already an object named {name!r}")
        object_file_names([*self.names, name])  # a name that cannot have a file: refused now
        with self._lock:
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
        self, origin, direction, positive: bool = True, start: bool = True
    ) -> ClickPoint:
        """A click in the 3D view (a ray from the viewer's camera) -> a click on a view: the
        front-most opaque Gaussian the ray passes through, projected into the session's view
        (or, for the first click, into the view that looks at it most nearly along the ray)."""
        point = pick_gaussian(self.gaussians, origin, direction)
        views = [self.view] if self.view is not None else range(len(self.cameras))
        view, x, y = view_for_point(self.cameras, self.depths, point, direction, views)
        return self.add_click(view, x, y, positive, point=point, start=start)

    def clear(self) -> None:
        """Forget every object and click (the labels too); the rendered views stay."""
        self.stop()
        with self._lock:
            self.objects, self.clicks, self.view, self.current = [], [], None, None
            self._run = None
            self.labels = np.full(len(self.gaussians), -1, np.int64)
            self.progress = Progress(total=len(self.cameras))

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
            votes = VoteAccumulator(len(self.gaussians), len(prompt.names), self.vote, self.device)
            self._run = Run(
                stream=self.segmenter.stream(self.frames, prompt),
                votes=votes,
                voting=set(select_frames(len(self.frames), self.vote)),
                masks=[None] * len(self.frames),
            )
            self.progress = Progress(total=len(self.frames), state="running", message="")
        self.resume()

    def resume(self) -> None:
        """Carry on a stopped run from its next view (nothing to do when it is done)."""
        with self._lock:
            run = self._run
            if run is None or run.finished or self.running:
                return
            self._stop.clear()
            self.progress.state = "running"
            self._thread = threading.Thread(target=self._work, args=(run,), daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop after the view in hand; the labels made so far stay."""
        thread = self._thread
        if thread is not None and thread.is_alive():
            self._stop.set()
            thread.join()
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

    def _work(self, run: Run) -> None:
        since_update = 0
        try:
            while not self._stop.is_set():
                item = next(run.stream, None)
                if item is None:
                    run.finished = True
                    break
                i, mask = item
                run.masks[i] = mask
                self.progress.segmented += 1
                if i in run.voting:
                    where = f"mask of view {i}"
                    run.votes.add_view(self.gaussians, self.cameras[i], mask, self.backend, where)
                    self.progress.voted += 1
                    since_update += 1
                    if self.progress.voted == 1 or since_update >= self.recolour_every:
                        self._publish(run)
                        since_update = 0
            self.progress.state = "done" if run.finished else "stopped"
            self._publish(run)
        except Exception as exc:  # shown in the GUI, re-raised by wait()
            self.progress.state, self.progress.message = "failed", f"{type(exc).__name__}: {exc}"
            if self.on_update is not None:
                self.on_update(self.labels, self.progress)

    def _publish(self, run: Run) -> None:
        """Labels from the histogram so far (the vote's rule, then its fill)."""
        result = self.vote_result(run)
        with self._lock:
            if run is not self._run:  # a newer click has started another run
                return
            self.labels = result.assigned.cpu().numpy().astype(np.int64)
            self.progress.seconds = time.perf_counter() - run.started
            p = self.progress
            p.message = f"{p.voted} of {len(run.voting)} views voted ({p.seconds:.1f} s)"
        if self.on_update is not None:
            self.on_update(self.labels, self.progress)

    def vote_result(self, run: Run) -> VoteResult:
        labels, labelled, hist, _ = run.votes.finalize_filled(self.gaussians.means)
        voted = sorted(i for i in run.voting if run.masks[i] is not None)
        return VoteResult(labels, labelled, hist, voted, {"num_masks": len(voted)})

    # --- take it with you --------------------------------------------------------------------

    def segmentation(self) -> Segmentation:
        """What the session holds as `segment_scene` gives it (views without a mask yet, after
        a Stop, carry an empty one)."""
        run = self._run
        if run is None or self.progress.voted == 0:
            raise PromptError("nothing to export yet: click on the object and let a view vote")
        masks = [m if m is not None else np.zeros(f.shape[:2], np.int64)
                 for m, f in zip(run.masks, self.frames, strict=True)]  # fmt: skip
        return Segmentation(
            self.labels.copy(), self.names, self.vote_result(run), list(self.cameras),
            self.frames, masks, {"render_s": self.render_seconds}, self.view or 0,
        )  # fmt: skip

    def export(
        self,
        out: str | Path,
        *,
        scene: Path | None = None,
        info: dict | None = None,
        overwrite: bool = False,
        record: bool = True,
    ) -> Path:
        """The folder `sagonline segment` writes (objects/<name>.ply, scene_without_<name>.ply,
        labels.npy, labels.json with this session's prompt, the recording): `sagonline segment
        --prompts OUT/labels.json` reproduces it without the browser."""
        seg = self.segmentation()
        check_objects_were_found(seg)
        parsed = self.parsed()
        full = {
            "scene": str(scene) if scene else None,
            "prompt": parsed.record(self.cameras),
            "segmenter": {"kind": self.segmenter_kind, "options": []},
            "vote": asdict(self.vote),
            "viewer": {"views_voted": self.progress.voted, "views": len(self.cameras),
                       "state": self.progress.state},
            **(info or {}),
        }  # fmt: skip
        inputs = [scene] if scene else []
        return write_segment_folder(
            Path(out), self.gaussians, seg, scene, full, backend=self.backend,
            device=self.device, record=record, overwrite=overwrite, inputs=inputs,
        )  # fmt: skip
