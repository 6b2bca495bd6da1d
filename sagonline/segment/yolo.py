"""YOLO instance segmentation with a tracker (extra: `pip install -e '.[yolo]'`).

Automatic: no prompt needed. Each frame is segmented by an ultralytics YOLO segmentation
model, detections are associated across frames by its tracker (ByteTrack or BoT-SORT, config
files shipped with ultralytics), and every track id gets one label (1, 2, ... in order of
first appearance), so a vehicle keeps its label through the video (KITTI-360). Detections the
tracker has not confirmed yet carry no id and are left as background. `classes` filters by
COCO id or name (default: vehicles); text prompts, when given, name the classes instead.

Nothing is downloaded: `weights` must be a local .pt file; `model_yaml` (e.g.
"yolo11n-seg.yaml") builds the same network with random weights, for tests.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sagonline.core.plugins import SEGMENTERS
from sagonline.scene.io.checkpoints import refuse_untrusted, unsafe_reason
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import Prompt

VEHICLES = ("car", "bus", "truck", "motorcycle", "train")


def _require_ultralytics():
    from sagonline.segment.compat import import_torchvision

    os.environ.setdefault("YOLO_OFFLINE", "1")
    try:
        import_torchvision()
        from ultralytics import YOLO
    except ImportError as exc:
        raise RuntimeError(
            "segmenter 'yolo' needs ultralytics: pip install -e '.[yolo]' "
            "(ultralytics-opencv-headless)"
        ) from exc
    return YOLO


class TrackLabeler:
    """Maps tracker ids to stable labels 1..K and rasterises one frame's detections."""

    def __init__(self):
        self.label_of: dict[int, int] = {}

    def label(self, track_id: int) -> int:
        if track_id not in self.label_of:
            self.label_of[track_id] = len(self.label_of) + 1
        return self.label_of[track_id]

    def rasterize(
        self,
        shape: tuple[int, int],
        polygons: list[np.ndarray],
        track_ids: list[int | None],
        scores: list[float],
    ) -> np.ndarray:
        """Detections drawn in order of increasing score (the most confident on top)."""
        for tid in track_ids:  # labels follow detection order, drawing follows score
            if tid is not None:
                self.label(tid)
        out = np.zeros(shape, np.int32)  # OpenCV draws into int32, not int64
        for k in np.argsort(scores, kind="stable"):
            if track_ids[k] is None or len(polygons[k]) < 3:
                continue
            cv2.fillPoly(out, [np.round(polygons[k]).astype(np.int32)], self.label(track_ids[k]))
        return out.astype(np.int64)


@dataclass
class YOLOConfig:
    """YOLO instance segmentation and tracking (`segmenter=yolo`)."""

    weights: str | None = None
    """REQUIRED: a local weights file, e.g. /path/to/yolo11n-seg.pt (nothing is downloaded)."""
    model_yaml: str | None = None
    """A model YAML built with random weights instead (tests only), e.g. yolo11n-seg.yaml."""
    classes: list[str] | None = field(default_factory=lambda: list(VEHICLES))
    """The class names kept; None: every class."""
    conf: float = 0.25
    """Detections below this confidence are dropped."""
    iou: float = 0.5
    """Non-maximum suppression's IoU threshold."""
    imgsz: int = 640
    """The model's input size in pixels."""
    tracker: str = "bytetrack.yaml"
    """ultralytics' tracker config: bytetrack.yaml or botsort.yaml."""
    device: str = "cpu"
    """Where the model runs (follows the run's `device`)."""
    trust_checkpoint: bool = False
    """Load weights that need arbitrary unpickling (only files you trust; never taken from a
    run folder)."""

    def __post_init__(self) -> None:
        from sagonline.core.settings import check_settings

        check_settings(
            "segmenter",
            conf=(0 <= self.conf <= 1, self.conf, "in [0, 1]"),
            iou=(0 <= self.iou <= 1, self.iou, "in [0, 1]"),
            imgsz=(32 <= self.imgsz <= 4096, self.imgsz, "in [32, 4096]"),
            tracker=(
                self.tracker in ("bytetrack.yaml", "botsort.yaml"),
                self.tracker,
                "bytetrack.yaml or botsort.yaml",
            ),
        )


@SEGMENTERS.register("yolo", YOLOConfig)
class YOLOSegmenter(VideoSegmenter):
    """YOLO instance segmentation + tracker from a local weights file (extra: .[yolo])."""

    name = "yolo"
    reads = ()

    def __init__(
        self,
        weights: str | None = None,
        model_yaml: str | None = None,
        classes: list | None = VEHICLES,
        conf: float = 0.25,
        iou: float = 0.5,
        imgsz: int = 640,
        tracker: str = "bytetrack.yaml",
        device: str = "cpu",
        trust_checkpoint: bool = False,
    ):
        if weights is None and model_yaml is None:
            raise ValueError(
                "segmenter 'yolo' needs a local weights file: set "
                "segmenter.weights=/path/to/yolo11n-seg.pt (nothing is downloaded)"
            )
        if weights is not None and not os.path.isfile(weights):
            raise FileNotFoundError(f"segmenter.weights={weights}: no such file")
        self.weights, self.model_yaml, self.classes = weights, model_yaml, classes
        self.conf, self.iou, self.imgsz = conf, iou, imgsz
        self.tracker, self.device = tracker, device
        self.trust_checkpoint = trust_checkpoint

    def weight_files(self) -> list[str]:
        return [self.weights] if self.weights else []

    def load_model(self):
        """The YOLO model from `weights` (or `model_yaml`); a file that does not load stops
        with the option's name. Weights are loaded by ultralytics' restricted loader
        (weights_only, its own model classes allow-listed): a file that needs arbitrary
        unpickling is refused unless `trust_checkpoint`."""
        YOLO = _require_ultralytics()
        from ultralytics.nn import tasks

        restricted = self.weights is not None and not self.trust_checkpoint
        safe_load = getattr(tasks, "_SafeLoad", None)
        if restricted and not (safe_load is not None and safe_load.SUPPORTED):
            refuse_untrusted(
                "segmenter.weights",
                Path(self.weights),
                "this ultralytics version has no restricted loader",
                "segmenter.trust_checkpoint",
            )
        previous = tasks.SAFE_LOAD
        tasks.SAFE_LOAD = previous or restricted
        try:
            return YOLO(self.weights or self.model_yaml, task="segment")
        except Exception as exc:  # ultralytics raises many kinds on a bad file
            if restricted and "outside the supported" in str(exc):
                refuse_untrusted(
                    "segmenter.weights",
                    Path(self.weights),
                    "it references types outside ultralytics' model classes: "
                    + unsafe_reason(exc.__cause__ or exc),
                    "segmenter.trust_checkpoint",
                )
            option = "weights" if self.weights else "model_yaml"
            raise ValueError(
                f"segmenter.{option}={self.weights or self.model_yaml}: YOLO could not load it "
                f"({type(exc).__name__}: {exc})"
            ) from exc
        finally:
            tasks.SAFE_LOAD = previous

    def check(self) -> None:
        self.load_model()

    def class_ids(self, names: dict[int, str], prompt: Prompt) -> list[int] | None:
        wanted = prompt.texts or self.classes
        if wanted is None:
            return None
        by_name = {v: k for k, v in names.items()}
        ids = []
        for c in wanted:
            if isinstance(c, int) or str(c).isdigit():
                ids.append(int(c))
            elif c in by_name:
                ids.append(by_name[c])
            else:
                raise ValueError(
                    f"segmenter 'yolo': class {c!r} is not one of the model's {len(names)} classes"
                )
        return ids

    def _segment(self, frames, prompt: Prompt, ground_truth):
        model = self.load_model()
        classes = self.class_ids(model.names, prompt)
        labeler = TrackLabeler()
        masks, seconds = [], []
        for frame in frames:
            start = time.perf_counter()
            r = model.track(
                np.ascontiguousarray(frame[..., ::-1]),
                persist=True,
                tracker=self.tracker,
                classes=classes,
                conf=self.conf,
                iou=self.iou,
                imgsz=self.imgsz,
                device=self.device,
                verbose=False,
            )[0]
            polygons, ids, scores = [], [], []
            if r.masks is not None and r.boxes is not None:
                track = r.boxes.id
                for k, poly in enumerate(r.masks.xy):
                    polygons.append(poly)
                    ids.append(None if track is None else int(track[k]))
                    scores.append(float(r.boxes.conf[k]))
            masks.append(labeler.rasterize(frame.shape[:2], polygons, ids, scores))
            seconds.append(time.perf_counter() - start)
        return masks, seconds
