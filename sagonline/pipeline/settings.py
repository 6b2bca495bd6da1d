"""How a scene is run, whichever front end runs it (`stage_one.StageOne`, Stage II, the
diagnosis): one dataclass, filled from the evaluation's config by `bench.job.settings_from`."""

from __future__ import annotations

from dataclasses import dataclass, field

from sagonline.vote.feedback import FeedbackConfig


@dataclass
class PipelineSettings:
    """How a scene is run: the image renderer and the vote's implementation, each resolved on
    its own for the device (`render.backends.plan_backends`), the label render's threshold, the
    metrics' resize rule, progress bars, the render background, consensus feedback."""

    backend: str = "auto"
    vote_backend: str = "auto"
    device: str = "cpu"
    label_min_weight: float = 0.2
    resize: str = "pred_to_gt"
    progress: bool = True
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    diagnose: bool = True
