"""The typed root configs: `EvalConfig` (`python -m bench.runners.eval`) and
`ScenesConfig` (`python -m bench.runners.scenes`), registered as Hydra schemas, and the config
groups of the plug-ins.

conf/eval.yaml and conf/scenes.yaml, and the groups they pick from, only select and override:
each default is stated once, on its field below or in the library's own settings dataclasses
(VoteConfig, RefineConfig, FeedbackConfig, FitConfig, and each plug-in's config). Segmenters
and datasets are plug-ins (`sagonline.core.plugins`): every registered one is a Hydra option
(`segmenter=<key>`, `dataset=<key>`) whose node is its typed config plus `kind` (the registry
key) and `name` (how runs and reports name it); conf/ holds only presets and data locations.
A wrong type or an unknown key fails at composition, naming the key, `+key=...` included; a
value out of its range fails at `to_config`, the one conversion each entry point makes, before
any work. Below the entry points nothing reads a DictConfig, and no object is built from a
class name in a config: plug-ins are built from the registry by key.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from sagonline.core.machine import DEVICE_DEFAULT, resolve_device
from sagonline.fitting import FitConfig
from sagonline.pipeline.settings import (
    LabelRenderSettings,
    MetricsSettings,
    PipelineSettings,
    RendererSettings,
)
from sagonline.refine import RefineConfig
from sagonline.segment.corruption import MaskCorruption
from sagonline.vote.consensus import VoteConfig
from sagonline.vote.feedback import FeedbackConfig


@dataclass
class RefineStage(RefineConfig):
    """Stage II as the harness runs it: the student's settings and whether it runs."""

    enabled: bool = True
    """Train the student (refine=student), or score the fused labels alone (refine=none)."""


@dataclass
class EvalConfig:
    """One evaluation: a dataset, a segmenter, the vote, optional Stage II, where outputs go."""

    dataset: Any = MISSING
    """The dataset group: `kind` (its registry key), `name`, `root` and the `adapter`'s
    settings (`sagonline.datasets.configs`)."""
    segmenter: Any = MISSING
    """The segmenter group: `kind` (its registry key), `name` and its settings (each
    segmenter's config dataclass)."""
    corrupt: MaskCorruption = field(default_factory=MaskCorruption)
    """Corrupt any segmenter's masks before they vote (robustness studies; off by default)."""
    consensus: VoteConfig = field(default_factory=VoteConfig)
    renderer: RendererSettings = field(default_factory=RendererSettings)
    refine: RefineStage = field(default_factory=lambda: RefineStage(enabled=False))
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    label_render: LabelRenderSettings = field(default_factory=LabelRenderSettings)
    metrics: MetricsSettings = field(default_factory=MetricsSettings)
    device: str = DEVICE_DEFAULT
    """auto (the GPU when CUDA is available, else the CPU), cpu, cuda or cuda:N; resolved and
    checked before any work (the run records the device it resolved to)."""
    seed: int = 0
    """Seeds the prompts' clicks, the noisy oracle, mask selection and the student."""
    record: bool = True
    """Write recording.rrd (rerun) into the run directory."""
    overwrite: bool = False
    """A finished run directory: the same config and inputs are skipped, others refused; true
    replaces it."""
    progress: bool = PipelineSettings.progress
    """Progress bars (always off when CI=true or off a terminal)."""
    cache: bool = True
    """Cache the stages' outputs, so an interrupted run resumes."""
    threads: int | None = None
    """Threads of this job's torch ops and kernels; None: the cores shared among parallel jobs."""
    diagnose: bool = PipelineSettings.diagnose
    """Sort every scored view's wrong pixels by cause (the fit, the vote, the 2D segmenter:
    `sagonline.score.diagnosis`) into per_view.csv, metrics.json and the recording."""
    cache_dir: str | None = ".cache/stages"
    """Where the stages' outputs are cached: one folder shared by every run and sweep (the
    stages are keyed by their inputs' content, so sharing is safe; `make clean-cache` empties
    it); None: a cache inside each run folder."""


@dataclass
class ScenesConfig:
    """`make scenes`: fit each scene of a dataset."""

    dataset: Any = MISSING
    """The dataset group, whose adapter says where the captures are."""
    fit: FitConfig = field(default_factory=FitConfig)
    scene: str | None = None
    """One scene of the dataset; None: all of them."""
    overwrite: bool = False
    """Fit again over a finished fit (a scene that is not ours is kept as a .bak file)."""
    finish: bool = False
    """Apply the steps the recipe runs after the last iteration (`fit.pose_view_clearance`) to
    a scene fitted before they existed: it becomes what a fit with this recipe writes."""
    finish_from: str | None = None
    """A finished fit of the same seed to start from, by its variant ('' or null-like
    `default`: gaussians/): taken as this recipe's state after the last iteration, so only the
    steps after it run (`fit.carve_views`' carve and polish). Its recipe must be this one up
    to those steps; refused otherwise."""
    progress: bool = True
    """Progress bars (always off when CI=true or off a terminal)."""
    device: str = FitConfig.device
    """The fit's device (`FitConfig.device`): cpu, the compiled kernel; cuda, gsplat; auto, cuda
    when available. A GPU fit is its own recipe (`fit=paper device=cuda`)."""
    seed: int = 0
    """Seeds the start points, densification noise and held-out split order."""
    variant: str | None = None
    """The fit's folder, gaussians-<variant>/ for seed 0 and gaussians-<variant>-seed<k>/ for
    seed k (null: gaussians/, gaussians-seed<k>/); the evaluation reads it with
    dataset.adapter.fit=<variant>[-seed<k>]. A plain name, never a path."""

    def __post_init__(self) -> None:
        from sagonline.core.settings import check_settings
        from sagonline.datasets.fits import is_variant_name

        check_settings(
            "scenes",
            variant=(
                self.variant is None or is_variant_name(self.variant),
                self.variant,
                "a plain name (letters, digits, - _ .), never a path",
            ),
            seed=(0 <= self.seed < 2**31, self.seed, "in [0, 2^31)"),
        )


# Plug-in settings of these names follow the run's own (`seed=1` reseeds every plug-in).
ROOT_SETTINGS = {"seed": "${seed}", "device": "${device}"}


def register_schemas_or_exit() -> None:
    """`register_schemas`, a plug-in that fails to load said in one line naming it (exit 2)
    instead of a traceback from inside Hydra."""
    from sagonline.core.plugins import PluginError, one_line

    try:
        register_schemas()
    except PluginError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        raise SystemExit(2) from None


def register_schemas() -> None:
    """The root schemas, the settings groups' schemas and one option per registered plug-in,
    in Hydra's ConfigStore (the entry points call this before composing; nothing registers on
    import)."""
    from hydra.core.config_store import ConfigStore

    from sagonline.core.plugins import DATASETS, SEGMENTERS, VOTE_RULES

    store = ConfigStore.instance()
    store.store(name="eval_schema", node=EvalConfig)
    store.store(name="scenes_schema", node=ScenesConfig)
    store.store(group="consensus", name="schema", node=VoteConfig)
    for plugin in VOTE_RULES:
        store.store(group="consensus", name=plugin.key, node=vote_node(plugin.key))
    store.store(group="fit", name="schema", node=FitConfig)
    store.store(group="refine", name="schema", node=RefineStage)
    store.store(group="feedback", name="schema", node=FeedbackConfig)
    for plugin in SEGMENTERS:
        store.store(group="segmenter", name=plugin.key, node=segmenter_node(plugin))
    for plugin in DATASETS:
        store.store(group="dataset", name=plugin.key, node=dataset_node(plugin))


def follow_root(node: DictConfig) -> DictConfig:
    """Settings named in ROOT_SETTINGS, at any depth of a plug-in's node, interpolated from the
    run's own."""
    for key in list(node.keys()):
        value = node._get_node(key)
        if isinstance(value, DictConfig):
            follow_root(value)
        elif key in ROOT_SETTINGS:
            node[key] = ROOT_SETTINGS[key]
    return node


def vote_node(method: str) -> DictConfig:
    """A vote rule's option: VoteConfig with its method (settings it does not read stay at
    their defaults; changing one is refused, naming it)."""
    node = OmegaConf.structured(VoteConfig(method=method))
    return follow_root(node)


def segmenter_node(plugin) -> DictConfig:
    """A segmenter's option: its typed config, `kind` and `name`."""
    node_class = dataclasses.make_dataclass(
        f"{plugin.config.__name__}Node",
        [("kind", str, field(default=plugin.key)), ("name", str, field(default=plugin.key))],
        bases=(plugin.config,),
    )
    return follow_root(OmegaConf.structured(node_class))


def dataset_node(plugin) -> DictConfig:
    """A dataset's option: `kind`, `name`, `root` (datasets/<key>) and the adapter's typed
    settings, whose own `name` and `root` follow the dataset's."""
    adapter = follow_root(OmegaConf.structured(plugin.config))
    for key, value in (("root", "${dataset.root}"), ("name", "${dataset.name}")):
        if key in adapter:
            adapter[key] = value
    root = "" if plugin.key == "synthetic" else f"datasets/{plugin.key}"
    return OmegaConf.create(
        {"kind": plugin.key, "name": plugin.key, "root": root, "adapter": adapter}
    )


def node_values(node: Any) -> Any:
    """A plug-in node (config dataclasses, mappings, lists, nested) as plain dicts and lists."""
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        return dataclasses.asdict(node)
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    if isinstance(node, Mapping):
        return {k: node_values(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [node_values(v) for v in node]
    return node


def to_config(cfg: DictConfig, schema: type):
    """The composed config as `schema` (EvalConfig or ScenesConfig): the one conversion an
    entry point makes. A key the schema does not have (also one added with `+key=...`), a
    value of the wrong type or out of its range stops here, naming its key. The plug-ins'
    nodes come out as plain dicts, checked against their registered configs."""
    try:
        refuse_unknown_keys(cfg)
        if cfg.get("device") == DEVICE_DEFAULT:  # resolved once: `${device}` reads the real one
            cfg.device = resolve_device(DEVICE_DEFAULT)
        typed = OmegaConf.merge(OmegaConf.structured(schema), cfg)
        check_boolean_overrides(typed)
        out = OmegaConf.to_object(typed)
        for group in ("dataset", "segmenter"):
            if hasattr(out, group):
                setattr(out, group, node_values(getattr(out, group)))
        check_plugin_nodes(out)
        check_dataset_name(out)
        return out
    except (ValueError, TypeError, KeyError) as exc:
        from sagonline.core.plugins import one_line

        print(f"error: {one_line(exc)}", file=sys.stderr)
        raise SystemExit(2) from None


def check_boolean_overrides(typed) -> None:
    """A command line's `key=2` on a true/false setting (OmegaConf reads any number as true)
    stops here, naming the key."""
    from hydra.core.hydra_config import HydraConfig

    try:
        overrides = list(HydraConfig.get().overrides.task)
    except ValueError:  # composed directly (tests): no command line
        return
    for arg in overrides:
        key, sep, value = arg.lstrip("+~").partition("=")
        if not sep or "," in value:
            continue
        if value.strip().lower() not in ("true", "false") and isinstance(
            OmegaConf.select(typed, key, default=None), bool
        ):
            raise ValueError(f"{key}={value}: must be true or false")


def check_dataset_name(cfg) -> None:
    """dataset.name names the run's folder (runs/<name>/...) and its protocol id: a plain name,
    never a path (`../../x` wrote the run outside runs/)."""

    name = (getattr(cfg, "dataset", None) or {}).get("name")
    if name is None:
        return
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", name):
        raise ValueError(
            f"dataset.name={name!r}: a name of letters, digits, '_', '-' and '.' (it names the "
            "run's folder and its protocol id), not a path"
        )
    if ".." in name:
        raise ValueError(f"dataset.name={name!r}: '..' is not allowed in a name")


def refuse_unknown_keys(cfg: DictConfig, prefix: str = "") -> None:
    """Stop on a key that a typed node of the composed config does not have. Hydra lets
    `+key=...` add one to a typed node, and OmegaConf's conversion would then drop it: the
    run would go on without the setting the user meant."""
    kind = OmegaConf.get_type(cfg)
    fields = {f.name for f in dataclasses.fields(kind)} if dataclasses.is_dataclass(kind) else None
    for key in cfg:
        if key == "hydra" and not prefix:
            continue
        name = f"{prefix}{key}"
        if fields is not None and key not in fields:
            raise KeyError(f"{name}: no such setting (misspelt? a '+' does not add one)")
        value = cfg._get_node(key)
        if isinstance(value, DictConfig) and not value._is_missing() and not value._is_none():
            refuse_unknown_keys(value, name + ".")


DATASET_NODE_KEYS = ("kind", "name", "root", "adapter")


def check_plugin_nodes(cfg) -> None:
    """The dataset's and segmenter's settings checked against their registered configs."""
    from sagonline.core.plugins import DATASETS, SEGMENTERS

    for group, registry in (("segmenter", SEGMENTERS), ("dataset", DATASETS)):
        node = getattr(cfg, group, None)
        if node is None:
            continue
        kind = node.get("kind")
        if kind not in registry:
            raise ValueError(f"{group}.kind={kind!r}: no such {registry.what} ({registry.keys()})")
        if group == "dataset":
            unknown = sorted(set(node) - set(DATASET_NODE_KEYS))
            if unknown:
                raise KeyError(
                    f"dataset.{unknown[0]}: no such setting (dataset.adapter.* holds "
                    "the dataset's settings)"
                )
        from sagonline.core.plugins import NODE_KEYS

        values = (
            node["adapter"]
            if group == "dataset"
            else {k: v for k, v in node.items() if k not in NODE_KEYS}
        )
        registry[kind].settings(
            values, where=f"{group}" + (".adapter" if group == "dataset" else "")
        )
