"""How a scene is run, whichever front end runs it (`stage_one.StageOne`, Stage II, the
diagnosis): one dataclass, filled from the evaluation's config by
`bench.runners.job.settings_from`."""

from __future__ import annotations

from dataclasses import dataclass, field

from sagonline.core.settings import check_settings
from sagonline.render.api import LABEL_MIN_WEIGHT
from sagonline.scene.cameras import Camera
from sagonline.vote.feedback import FeedbackConfig


@dataclass
class PipelineSettings:
    """How a scene is run: the image renderer and the vote's implementation, each resolved on
    its own for the device (`render.backends.plan_backends`), the label render's threshold and
    size, the metrics' resize rule, progress bars, the render background, consensus feedback."""

    backend: str = "auto"
    vote_backend: str = "auto"
    device: str = "cpu"
    label_min_weight: float = LABEL_MIN_WEIGHT
    """A label render's pixel takes a label where labelled Gaussians make up this much of it."""
    label_size: str = "render"
    """The scored label renders' size: render (the eval view's camera) or truth (that camera
    rescaled to the view's ground-truth size)."""
    resize: str = "pred_to_gt"
    progress: bool = True
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    diagnose: bool = True

    def __post_init__(self) -> None:
        size, weight = self.label_size, self.label_min_weight
        check_settings(
            "label_render",
            min_weight=(0 <= weight <= 1, weight, "a blend weight in [0, 1]"),
            size=(size in LABEL_SIZES, size, f"one of {LABEL_SIZES}"),
        )

    def scored_camera(self, view) -> Camera:
        """The camera an eval view's labels are rendered with for scoring (`label_size`)."""
        if self.label_size == "truth":
            h, w = view.gt.shape[:2]
            return view.camera.scaled(w, h)
        return view.camera


LABEL_SIZES = ("render", "truth")
