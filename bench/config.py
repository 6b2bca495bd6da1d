"""The typed root configs: `EvalConfig` (`python -m bench.eval`) and `ScenesConfig`
(`python -m bench.scenes`), registered as Hydra schemas.

conf/eval.yaml and conf/scenes.yaml, and the groups they pick from, only select and override:
each default is stated once, on its field below or in the library's own settings dataclasses
(VoteConfig, RefineConfig, FeedbackConfig, FitConfig). A wrong type or an unknown key fails at
composition, naming the key; a value out of its range fails at `to_eval_config` /
`to_scenes_config`, the one conversion each entry point makes, before any work. Below the entry
points nothing reads a DictConfig. Datasets and segmenters are plug-ins: their nodes stay plain
dicts (`_target_` and the constructor's arguments) handed to `hydra.utils.instantiate`.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf

from sagonline.consensus import VoteConfig
from sagonline.datasets.configs import DATASET_CONFIGS
from sagonline.feedback import FeedbackConfig
from sagonline.fitting import FitConfig
from sagonline.refine import RefineConfig
from sagonline.segmenters.corruption import MaskCorruption


@dataclass
class RefineStage(RefineConfig):
    """Stage II as the harness runs it: the student's settings and whether it runs."""

    enabled: bool = True
    """Train the student (refine=student) or answer in the initial mode only (refine=none)."""


@dataclass
class RendererConfig:
    backend: str = "auto"
    """auto: the compiled kernel on the CPU, gsplat on CUDA; native | gsplat | torch (the
    readable PyTorch twin)."""


@dataclass
class LabelRenderConfig:
    min_weight: float = 0.2
    """A pixel takes a label where the labelled Gaussians' blend weight reaches this."""


@dataclass
class MetricsConfig:
    resize: str = "pred_to_gt"
    """pred_to_gt: predictions resized (nearest) to the ground truth; gt_to_pred: the reverse."""


@dataclass
class EvalConfig:
    """One evaluation: a dataset, a segmenter, the vote, optional Stage II, where outputs go."""

    dataset: Any = MISSING
    """The dataset group (conf/dataset/): `name`, `root` and the `adapter` plug-in."""
    segmenter: Any = MISSING
    """The segmenter group (conf/segmenter/): `name` and the plug-in's `_target_` and settings."""
    corrupt: MaskCorruption = field(default_factory=MaskCorruption)
    """Corrupt any segmenter's masks before they vote (robustness studies; off by default)."""
    consensus: VoteConfig = field(default_factory=VoteConfig)
    renderer: RendererConfig = field(default_factory=RendererConfig)
    refine: RefineStage = field(default_factory=lambda: RefineStage(enabled=False))
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    label_render: LabelRenderConfig = field(default_factory=LabelRenderConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    device: str = "cpu"
    """cpu, cuda or cuda:N; checked before any work."""
    seed: int = 0
    """Seeds the prompts' clicks, the noisy oracle, mask selection and the student."""
    record: bool = True
    """Write recording.rrd (rerun) into the run directory."""
    overwrite: bool = False
    """A finished run directory: the same config and inputs are skipped, others refused; true
    replaces it."""
    progress: bool = True
    """Progress bars (always off when CI=true)."""
    cache: bool = True
    """Cache the stages' outputs, so an interrupted run resumes."""
    threads: int | None = None
    """Threads of this job's torch ops and kernels; None: the cores shared among parallel jobs."""
    cache_dir: str | None = ".cache/stages"
    """Where the stages' outputs are cached: one folder shared by every run and sweep (the
    stages are keyed by their inputs' content, so sharing is safe; `make clean-cache` empties
    it); None: a cache inside each run folder."""


@dataclass
class ScenesConfig:
    """`make scenes`: fit each scene of a dataset."""

    dataset: Any = MISSING
    """The dataset group (conf/dataset/), whose adapter says where the captures are."""
    fit: FitConfig = field(default_factory=FitConfig)
    scene: str | None = None
    """One scene of the dataset; None: all of them."""
    overwrite: bool = False
    """Fit again over a finished fit (a scene that is not ours is kept as a .bak file)."""
    progress: bool = True
    """Progress bars (always off when CI=true)."""
    device: str = "cpu"
    """cpu: the compiled kernel; cuda: gsplat."""
    seed: int = 0
    """Seeds the start points, densification noise and held-out split order."""


def register_schemas() -> None:
    """The root schemas and the groups' schemas, in Hydra's ConfigStore (the entry points
    call this before composing; nothing registers on import)."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    store.store(name="eval_schema", node=EvalConfig)
    store.store(name="scenes_schema", node=ScenesConfig)
    store.store(group="consensus", name="schema", node=VoteConfig)
    store.store(group="fit", name="schema", node=FitConfig)
    store.store(group="refine", name="schema", node=RefineStage)
    store.store(group="feedback", name="schema", node=FeedbackConfig)
    for name, node in DATASET_CONFIGS.items():
        store.store(group="dataset/adapter", name=name, node=node)


def to_config(cfg: DictConfig, schema: type):
    """The composed config as `schema` (EvalConfig or ScenesConfig): the one conversion an
    entry point makes. A value out of its range stops here, naming its key."""
    try:
        typed = OmegaConf.merge(OmegaConf.structured(schema), cfg)
        return OmegaConf.to_object(typed)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
