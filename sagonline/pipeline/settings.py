"""How a scene is run, whichever front end runs it (`stage_one.StageOne`, Stage II, the
diagnosis, `segment`, the viewer): one dataclass of groups, each group the same dataclass the
evaluation's Hydra schema uses (`renderer`, `label_render`, `metrics`: one default and one name
per setting from `conf/` to the kernels). The device's default and its resolution are
`core.machine`'s."""

from __future__ import annotations

from dataclasses import dataclass, field

from sagonline.core.machine import DEVICE_DEFAULT, resolve_device
from sagonline.core.settings import check_settings
from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.scene.cameras import Camera
from sagonline.score.metrics import RESIZE_RULES
from sagonline.vote.feedback import FeedbackConfig

LABEL_SIZES = ("render", "truth")
RESIZES = tuple(RESIZE_RULES)


@dataclass
class RendererSettings:
    """Which implementation renders images and which runs the vote, each resolved on its own
    for the device (`render.backends.plan_backends`)."""

    backend: str = "auto"
    """Images: auto (the compiled kernel on the CPU; gsplat on CUDA, else torch); native |
    gsplat | torch (the readable PyTorch twin)."""
    vote_backend: str = "auto"
    """The vote and the label renders, resolved on their own: auto (the compiled kernel on the
    CPU; on CUDA triton, else gsplat, else torch); native | triton | gsplat | torch."""


@dataclass
class LabelRenderSettings:
    """How labels are rendered from the Gaussians' labels."""

    min_weight: float = LABEL_MIN_WEIGHT
    """A pixel takes a label where the labelled Gaussians' blend weight reaches this."""
    size: str = "render"
    """The scored label renders' size: render (the eval view's camera, e.g. the capture's
    `render_max_side`; resized to the ground truth by `metrics.resize`) or truth (the eval
    view's camera rescaled to its ground truth's size: no resize)."""

    def __post_init__(self) -> None:
        size, weight = self.size, self.min_weight
        check_settings(
            "label_render",
            min_weight=(0 <= weight <= 1, weight, "a blend weight in [0, 1]"),
            size=(size in LABEL_SIZES, size, f"one of {LABEL_SIZES}"),
        )


@dataclass
class MetricsSettings:
    """How predictions meet the ground truth."""

    resize: str = "pred_to_gt"
    """pred_to_gt: predictions resized (nearest) to the ground truth; gt_to_pred: the reverse."""

    def __post_init__(self) -> None:
        resize = self.resize
        check_settings("metrics", resize=(resize in RESIZES, resize, f"one of {RESIZES}"))


@dataclass
class PipelineSettings:
    """How a scene is run: the renderers, the label renders, the metrics' resize rule, the
    device ('auto' resolved here: `core.machine.resolve_device`), progress, the render
    background, consensus feedback and the diagnosis."""

    renderer: RendererSettings = field(default_factory=RendererSettings)
    label_render: LabelRenderSettings = field(default_factory=LabelRenderSettings)
    metrics: MetricsSettings = field(default_factory=MetricsSettings)
    device: str = DEVICE_DEFAULT
    """auto (the GPU when CUDA is available, else the CPU), cpu, cuda or cuda:N."""
    progress: bool = True
    """Progress bars (always off when CI=true or off a terminal)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The render background (a fit's own, where it has one)."""
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    diagnose: bool = True
    """Sort every scored view's wrong pixels by cause (the fit, the vote, the 2D segmenter:
    `sagonline.score.diagnosis`) into per_view.csv, metrics.json and the recording."""

    def __post_init__(self) -> None:
        self.device = resolve_device(self.device)

    def scored_camera(self, view) -> Camera:
        """The camera an eval view's labels are rendered with for scoring (`label_render.size`)."""
        if self.label_render.size == "truth":
            h, w = view.gt.shape[:2]
            return view.camera.scaled(w, h)
        return view.camera
