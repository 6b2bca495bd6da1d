"""Rerun recordings of a run: cameras, frames, masks, label renders, ground truth, per-view IoU
and the labelled Gaussians, with a default layout.

Entity layout (one recording per run, every scene under `scenes/<name>`):
- `.../trajectory/camera` (Transform3D + Pinhole, OpenCV axes) with its `rgb` and `segmenter`
  images, on the `frame` timeline: the frames sit in their frusta around the Gaussians, and
  scrubbing `frame` moves the camera along the trajectory;
- `.../eval/camera` with `rgb`, `prediction` (fused labels), `ground_truth` and, when Stage II
  ran, `refined`, on the `eval_view` timeline; `.../metrics/iou` (and `refined_iou`) scalars;
- `.../gaussians/labelled` coloured by label (ellipsoids up to ELLIPSOID_LIMIT Gaussians, points
  above), `.../gaussians/unlabelled` grey points (toggle it in the viewer), and
  `.../gaussians/confidence`: every voted Gaussian coloured by its winning share of the votes
  (dark: contested, bright: unanimous).
All masks are SegmentationImages under one AnnotationContext per scene, so a label has one colour
everywhere. The default blueprint shows, per scene, RGB | segmenter | fused labels | ground truth
(| refined), the per-view IoU below, and the 3D view beside them. Open with
`rerun recording.rrd` (the environment's own viewer: `viewer_command`).

The trajectory's frames are logged by a thread of the recorder's own, as the masks come: each
JPEG-encoded frame and mask took about 7 ms of a Stage I view on the host otherwise. Every
other call first waits for them (the log keeps its order), and so does `close`, which also
raises what any of them raised.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from sagonline.labels.colours import BACKGROUND_3D, label_colors

ELLIPSOID_LIMIT = 50_000  # larger scenes are drawn as points: ellipsoids would drown the viewer
FRAMES_WAITING = 8  # trajectory frames handed to the recorder's thread and not yet logged


def viewer_command(recording: Path) -> str:
    """The shell command that opens `recording` in the rerun viewer this environment installed
    (rerun-sdk's `rerun`, of the version that wrote it): `rerun` where PATH finds that one, else
    its path (relative to the working folder where it lies below it: `.venv/bin/rerun`, for a
    shell where the environment is not activated, which found no `rerun` or another one)."""
    import os
    import shlex
    import shutil
    import sysconfig

    own = Path(sysconfig.get_path("scripts")) / "rerun"
    found = shutil.which("rerun")
    if not own.is_file() or (found is not None and Path(found).resolve() == own.resolve()):
        viewer = "rerun"
    else:
        absolute = own.absolute()
        inside = absolute.is_relative_to(Path.cwd())
        viewer = os.path.relpath(absolute) if inside else str(absolute)
    return f"{shlex.quote(viewer)} {shlex.quote(str(recording))}"


class Recorder:
    """Writes a `.rrd` file; a disabled recorder accepts every call and writes nothing.
    `scenes` (names) and `refined` shape the default blueprint."""

    def __init__(
        self,
        path: str | Path | None,
        application_id: str = "sagonline",
        scenes: list[str] | None = None,
        refined: bool = False,
    ):
        self.path = Path(path) if path is not None else None
        self.rec = None
        self._thread: ThreadPoolExecutor | None = None
        self._waiting: list[Future] = []
        self._room = threading.BoundedSemaphore(FRAMES_WAITING)
        if self.path is not None:
            import rerun as rr

            self.rr = rr
            self.rec = rr.RecordingStream(application_id)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            blueprint = default_blueprint(scenes, refined) if scenes else None
            self.rec.save(str(self.path), default_blueprint=blueprint)

    @property
    def enabled(self) -> bool:
        return self.rec is not None

    def _at(self, timeline: str, index: int, frame: int | None = None) -> None:
        """Only `timeline` (and `frame` where given) set: data never lands on another
        timeline's last index."""
        self.rec.reset_time()
        self.rec.set_time(timeline, sequence=index)
        if frame is not None:
            self.rec.set_time("frame", sequence=frame)

    def _camera(self, path: str, camera) -> None:
        """Transform3D (world -> camera, OpenCV axes) + Pinhole of a view at `path`."""
        w2c = camera.world_to_cam.detach().double().cpu().numpy()
        self.rec.log(
            path,
            self.rr.Transform3D(
                translation=w2c[:3, 3],
                mat3x3=w2c[:3, :3],
                relation=self.rr.TransformRelation.ChildFromParent,
            ),
            self.rr.Pinhole(
                image_from_camera=camera.K.detach().double().cpu().numpy(),
                resolution=[camera.width, camera.height],
                camera_xyz=self.rr.ViewCoordinates.RDF,
                image_plane_distance=0.2,
            ),
        )

    def _mask(self, path: str, mask: np.ndarray) -> None:
        mask = np.asarray(mask)
        small = mask.size == 0 or int(mask.max()) < 256  # uint8 where the ids fit: half the bytes
        self.rec.log(path, self.rr.SegmentationImage(mask.astype(np.uint8 if small else np.uint16)))

    def _rgb(self, path: str, rgb: np.ndarray) -> None:
        """RGB frames JPEG-encoded (quality 90, by OpenCV: half rerun's time, and it lets other
        threads run): a tenth of the raw bytes."""
        bgr = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
        if not ok:
            raise ValueError(f"recording: {path}: a {rgb.shape} frame could not be JPEG-encoded")
        self.rec.log(path, self.rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))

    def _wait(self) -> None:
        """Until every trajectory frame handed to the recorder's thread is logged; raises what
        any of them raised."""
        waiting, self._waiting = self._waiting, []
        for future in waiting:
            future.result()

    def annotate(self, scene: str, names: list[str]) -> None:
        if not self.enabled:
            return
        self._wait()
        colors = label_colors(len(names))
        info = [(i, n, tuple(int(c) for c in colors[i])) for i, n in enumerate(names)]
        self.rec.log(f"scenes/{scene}", self.rr.AnnotationContext(info), static=True)

    def trajectory_frame(
        self,
        scene: str,
        index: int,
        rgb: np.ndarray,  # [H, W, 3] uint8, not changed afterwards
        mask: np.ndarray | None = None,  # [H, W] ids, not changed afterwards
        camera=None,
    ) -> None:
        """Trajectory frame `index` with the segmenter's mask, logged by the recorder's thread
        (at most FRAMES_WAITING wait; one more waits for room)."""
        if not self.enabled:
            return
        if self._thread is None:
            self._thread = ThreadPoolExecutor(1, thread_name_prefix="recording")
        self._room.acquire()
        future = self._thread.submit(self._trajectory_frame, scene, index, rgb, mask, camera)
        future.add_done_callback(lambda _: self._room.release())
        self._waiting.append(future)

    def _trajectory_frame(self, scene, index, rgb, mask, camera) -> None:
        self._at("frame", index)  # rerun's time is the calling thread's
        base = f"scenes/{scene}/trajectory/camera"
        if camera is not None:
            self._camera(base, camera)
        self._rgb(f"{base}/rgb", rgb)
        if mask is not None:
            self._mask(f"{base}/segmenter", mask)

    def eval_view(
        self,
        scene: str,
        index: int,
        rgb: np.ndarray,
        prediction: np.ndarray,
        ground_truth: np.ndarray,
        camera=None,
        iou: float | None = None,
        frame: int | None = None,
        diagnosis: np.ndarray | None = None,
    ) -> None:
        """Eval view `index`, also placed at trajectory `frame` (its own or the nearest view), so
        scrubbing `frame` shows the fused labels and ground truth beside the segmenter;
        `diagnosis`: (H, W, 3) the causes of its wrong pixels (`sagonline.score.diagnosis`)."""
        if not self.enabled:
            return
        self._wait()
        self._at("eval_view", index, frame)
        base = f"scenes/{scene}/eval/camera"
        if camera is not None:
            self._camera(base, camera)
        self._rgb(f"{base}/rgb", rgb)
        self._mask(f"{base}/prediction", prediction)
        self._mask(f"{base}/ground_truth", ground_truth)
        if diagnosis is not None:
            self._rgb(f"{base}/diagnosis", diagnosis)
        if iou is not None:
            self.rec.log(f"scenes/{scene}/metrics/iou", self.rr.Scalars(iou))

    def refined_view(
        self,
        scene: str,
        index: int,
        refined: np.ndarray,
        iou: float | None = None,
        frame: int | None = None,
    ) -> None:
        """Stage II's answer for eval view `index`, beside the initial one."""
        if not self.enabled:
            return
        self._wait()
        self._at("eval_view", index, frame)
        self._mask(f"scenes/{scene}/eval/camera/refined", refined)
        if iou is not None:
            self.rec.log(f"scenes/{scene}/metrics/refined_iou", self.rr.Scalars(iou))

    def gaussians(
        self,
        scene: str,
        gaussians,
        labels: np.ndarray,
        histogram: np.ndarray | None = None,
        max_points: int = 200_000,
    ) -> None:
        """The Gaussians: labelled ones in their label colour (ellipsoids up to
        ELLIPSOID_LIMIT, else points), unlabelled ones grey, and the vote's confidence.
        labels: (N,) int64, -1 unlabelled; histogram: (N, K) votes or weights."""
        if not self.enabled:
            return
        self._wait()
        rr, base = self.rr, f"scenes/{scene}/gaussians"
        means = gaussians.means.detach().cpu().numpy()
        labels = np.asarray(labels)
        labelled = labels >= 0
        self.rec.reset_time()
        on = np.flatnonzero(labelled)
        palette = label_colors(int(labels.max(initial=0)) + 1)
        palette[0] = BACKGROUND_3D  # black in masks; in 3D a visible neutral
        colors = palette[labels[on]]
        if len(means) <= ELLIPSOID_LIMIT:
            scales = gaussians.scales.detach().cpu().numpy()
            if scales.shape[1] == 2:  # surfels: a thin third axis
                scales = np.concatenate([scales, np.full((len(scales), 1), 1e-4)], 1)
            quats = gaussians.quats.detach().cpu().numpy()[:, [1, 2, 3, 0]]  # wxyz -> xyzw
            self.rec.log(
                f"{base}/labelled",
                rr.Ellipsoids3D(
                    centers=means[on],
                    half_sizes=scales[on],
                    quaternions=quats[on],
                    colors=colors,
                    class_ids=labels[on].astype(np.uint16),
                    fill_mode="solid",
                ),
                static=True,
            )
        else:
            step = max(1, len(on) // max_points)
            self.rec.log(
                f"{base}/labelled",
                rr.Points3D(
                    means[on][::step],
                    colors=colors[::step],
                    class_ids=labels[on][::step].astype(np.uint16),
                    radii=0.004,
                ),
                static=True,
            )
        off = np.flatnonzero(~labelled)[:: max(1, int((~labelled).sum()) // max_points)]
        self.rec.log(
            f"{base}/unlabelled",
            rr.Points3D(means[off], colors=(120, 120, 120), radii=0.003),
            static=True,
        )
        if histogram is not None:
            hist = np.asarray(histogram, dtype=np.float64)
            total = hist.sum(1)
            voted = np.flatnonzero(total > 0)[:: max(1, int((total > 0).sum()) // max_points)]
            share = hist[voted].max(1) / total[voted]
            import matplotlib

            ramp = (matplotlib.colormaps["viridis"](share)[:, :3] * 255).astype(np.uint8)
            self.rec.log(
                f"{base}/confidence",
                rr.Points3D(means[voted], colors=ramp, radii=0.004),
                static=True,
            )

    def close(self) -> None:
        """Log what waits, then write the file out; raises what any frame's logging raised
        (the file is written all the same)."""
        if not self.enabled:
            return
        try:
            self._wait()
        finally:
            if self._thread is not None:
                self._thread.shutdown()
            self.rec.flush()
            self.rec.disconnect()
            self.rec = None


def default_blueprint(scenes: list[str], refined: bool = False):
    """Per scene (one tab each): RGB | segmenter | fused labels | ground truth (| refined) over
    the per-view IoU, and the 3D view beside them."""
    import rerun.blueprint as rrb

    tabs = []
    for scene in scenes:
        base = f"/scenes/{scene}"
        traj, ev = f"{base}/trajectory/camera", f"{base}/eval/camera"
        images = [
            rrb.Spatial2DView(name="RGB", origin=traj, contents=["$origin/rgb"]),
            rrb.Spatial2DView(name="segmenter", origin=traj, contents=["$origin/segmenter"]),
            rrb.Spatial2DView(name="fused labels", origin=ev, contents=["$origin/prediction"]),
            rrb.Spatial2DView(name="ground truth", origin=ev, contents=["$origin/ground_truth"]),
        ]
        if refined:
            images.append(
                rrb.Spatial2DView(name="refined", origin=ev, contents=["$origin/refined"])
            )
        tabs.append(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Horizontal(*images),
                    rrb.TimeSeriesView(name="per-view IoU", origin=f"{base}/metrics"),
                    row_shares=[2, 1],
                ),
                rrb.Spatial3DView(name="3D", origin=base),
                column_shares=[3, 2],
                name=scene,
            )
        )
    return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)
