"""Rerun recordings of a run: frames, masks, label renders, ground truth and labelled Gaussians.

Entity layout (one recording per run, every scene under `scenes/<name>`):
- `.../trajectory/rgb`, `.../trajectory/segmenter` on the `frame` timeline;
- `.../eval/rgb`, `.../eval/prediction`, `.../eval/ground_truth` on the `eval_view` timeline;
- `.../gaussians` a static point cloud coloured by fused label (class ids).
All masks are SegmentationImages under one AnnotationContext, so a label has one colour
everywhere. Open with `rerun recording.rrd`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PALETTE = np.array(
    [
        [0, 0, 0],
        [230, 25, 75],
        [60, 180, 75],
        [255, 225, 25],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [210, 245, 60],
        [250, 190, 212],
        [0, 128, 128],
        [220, 190, 255],
        [170, 110, 40],
        [255, 250, 200],
        [128, 0, 0],
    ],
    dtype=np.uint8,
)


def label_colors(num_labels: int) -> np.ndarray:
    reps = int(np.ceil(num_labels / len(PALETTE)))
    return np.tile(PALETTE, (reps, 1))[:num_labels]


class Recorder:
    """Writes a `.rrd` file; a disabled recorder accepts every call and writes nothing."""

    def __init__(self, path: str | Path | None, application_id: str = "sagonline"):
        self.path = Path(path) if path is not None else None
        self.rec = None
        if self.path is not None:
            import rerun as rr

            self.rr = rr
            self.rec = rr.RecordingStream(application_id)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self.path))

    @property
    def enabled(self) -> bool:
        return self.rec is not None

    def annotate(self, scene: str, names: list[str]) -> None:
        if not self.enabled:
            return
        colors = label_colors(len(names))
        info = [(i, n, tuple(int(c) for c in colors[i])) for i, n in enumerate(names)]
        self.rec.log(f"scenes/{scene}", self.rr.AnnotationContext(info), static=True)

    def trajectory_frame(
        self, scene: str, index: int, rgb: np.ndarray, mask: np.ndarray | None = None
    ) -> None:
        if not self.enabled:
            return
        self.rec.set_time("frame", sequence=index)
        self.rec.log(f"scenes/{scene}/trajectory/rgb", self.rr.Image(rgb))
        if mask is not None:
            self.rec.log(
                f"scenes/{scene}/trajectory/segmenter",
                self.rr.SegmentationImage(mask.astype(np.uint16)),
            )

    def eval_view(
        self,
        scene: str,
        index: int,
        rgb: np.ndarray,
        prediction: np.ndarray,
        ground_truth: np.ndarray,
        refined: np.ndarray | None = None,
    ) -> None:
        if not self.enabled:
            return
        self.rec.set_time("eval_view", sequence=index)
        self.rec.log(f"scenes/{scene}/eval/rgb", self.rr.Image(rgb))
        self.rec.log(
            f"scenes/{scene}/eval/prediction",
            self.rr.SegmentationImage(prediction.astype(np.uint16)),
        )
        self.rec.log(
            f"scenes/{scene}/eval/ground_truth",
            self.rr.SegmentationImage(ground_truth.astype(np.uint16)),
        )
        if refined is not None:
            self.rec.log(
                f"scenes/{scene}/eval/refined", self.rr.SegmentationImage(refined.astype(np.uint16))
            )

    def gaussians(
        self,
        scene: str,
        means: np.ndarray,
        labels: np.ndarray,
        labelled: np.ndarray,
        max_points: int = 200_000,
    ) -> None:
        """Point cloud of Gaussian centres; labelled ones in their label colour, others grey."""
        if not self.enabled:
            return
        step = max(1, len(means) // max_points)
        means, labels, labelled = means[::step], labels[::step], labelled[::step]
        colors = label_colors(int(labels.max(initial=0)) + 1)[labels]
        colors[~labelled] = (120, 120, 120)
        self.rec.log(
            f"scenes/{scene}/gaussians",
            self.rr.Points3D(means, colors=colors, class_ids=labels.astype(np.uint16), radii=0.004),
            static=True,
        )

    def close(self) -> None:
        if self.enabled:
            self.rec.flush()
            self.rec.disconnect()
            self.rec = None
