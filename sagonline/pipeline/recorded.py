"""A finished evaluation run read back from its metrics.json, to redo its Stage I (`export`).

A run folder may come from anyone, so its metrics.json is data, never code: it names the
dataset and the segmenter by registry key (`kind`) with settings, and each is rebuilt from the
registries (`sagonline.core.plugins`) after its settings are checked against the plug-in's typed
config; every other group (vote, corruption, feedback, renderer) is checked against its own
dataclass. Nothing is built from a class name in the file, no checkpoint is unpickled on its
say-so (`trust_checkpoint` is turned off), and the cache keys it records are never trusted:
the stages are keyed again from today's inputs, taken from the run's cache where an entry
matches, and computed again where none does. The cache is only read, never written or
cleaned: its folder is one the file named.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sagonline.core.errors import DatasetError
from sagonline.core.machine import DEVICE_DEFAULT
from sagonline.core.plugins import DATASETS, PluginError, typed_settings
from sagonline.datasets.base import DatasetAdapter
from sagonline.pipeline.settings import (
    LabelRenderSettings,
    MetricsSettings,
    PipelineSettings,
    RendererSettings,
)
from sagonline.pipeline.stages import SegmenterRun, segmenter_run
from sagonline.score.run_metrics import MetricsFileError, RunMetrics
from sagonline.segment.corruption import MaskCorruption
from sagonline.vote.consensus import VoteConfig
from sagonline.vote.feedback import FeedbackConfig

# Runs written before the registries named their dataset by class path: these (compared as
# strings, never imported) are read as the registry keys beside them.
LEGACY_DATASETS = {
    "sagonline.datasets.generic.PosedMasksDataset": "generic",
    "sagonline.datasets.nvos.NVOSDataset": "nvos",
    "sagonline.datasets.spinnerf.SPInNeRFDataset": "spinnerf",
}
LEGACY_SEGMENTERS = {
    "sagonline.segment.classical.FlowWatershedSegmenter": "classical",
    "sagonline.segment.oracle.OracleSegmenter": "oracle",
    "sagonline.segment.sam2_video.SAM2VideoSegmenter": "sam2",
    "sagonline.segment.sam3_text.SAM3TextSegmenter": "sam3",
    "sagonline.segment.yolo.YOLOSegmenter": "yolo",
}


class RunFileError(DatasetError):
    """A run folder whose metrics.json cannot be read back; names the file and the key."""


@dataclass
class RecordedRun:
    """What redoing a run's Stage I takes, rebuilt from its metrics.json."""

    folder: Path
    adapter: DatasetAdapter
    segmenter: SegmenterRun
    vote: VoteConfig
    settings: PipelineSettings
    scenes: list[dict]
    cache_root: Path | None
    notes: list[str] = field(default_factory=list)


def read_metrics(run: Path) -> RunMetrics:
    """The run's record (its metrics.json); RunFileError naming the file otherwise."""
    try:
        return RunMetrics.of_run(Path(run))
    except MetricsFileError as exc:
        raise RunFileError(str(exc)) from None


def _group(config: dict, key: str, path: Path) -> dict:
    value = config.get(key)
    if not isinstance(value, dict):
        raise RunFileError(f"{path}: config.{key} is {type(value).__name__}, not an object")
    return value


def read_recorded_run(run: str | Path, device: str | None = None) -> RecordedRun:
    """Rebuild a finished run's dataset, segmenter and settings from its metrics.json (see the
    module docstring). `device` replaces the recorded one (a CUDA run exported on a CPU)."""
    run = Path(run)
    if run.exists() and not run.is_dir():
        raise RunFileError(f"{run}: a file; export takes a finished evaluation's run folder")
    path = run / "metrics.json"
    metrics = read_metrics(run)
    config = metrics.config
    if not metrics.recorded("config") or not config:
        raise RunFileError(f"{path}: no 'config' object (not a run of bench.runners.eval)")
    notes: list[str] = []
    try:
        adapter = _dataset(_group(config, "dataset", path))
        corrupt = typed_settings(MaskCorruption, config.get("corrupt") or {}, "config.corrupt")
        segmenter_node = _segmenter_node(_group(config, "segmenter", path))
        if segmenter_node.get("trust_checkpoint"):
            notes.append(
                "the run trusted its segmenter's checkpoint (trust_checkpoint=true); export "
                "never does: masks that must be computed again load weights_only"
            )
        segmenter = segmenter_run(segmenter_node, corrupt, check=False, untrusted=True)
        vote = typed_settings(VoteConfig, _group(config, "consensus", path), "config.consensus")
        feedback = typed_settings(FeedbackConfig, config.get("feedback") or {}, "config.feedback")
    except (PluginError, ValueError, TypeError) as exc:
        raise RunFileError(f"{path}: {exc}") from None
    try:
        settings = PipelineSettings(
            typed_settings(RendererSettings, config.get("renderer") or {}, "config.renderer"),
            typed_settings(
                LabelRenderSettings, config.get("label_render") or {}, "config.label_render"
            ),
            typed_settings(MetricsSettings, config.get("metrics") or {}, "config.metrics"),
            device=device or str(config.get("device") or DEVICE_DEFAULT),
            progress=False,
            feedback=feedback,
        )
    except (PluginError, ValueError, TypeError) as exc:
        raise RunFileError(f"{path}: {exc}") from None
    scenes = metrics.scenes
    if not all(isinstance(s, dict) for s in scenes):
        raise RunFileError(f"{path}: 'scenes' is not a list of scene rows")
    recorded = metrics.cache_root
    cache_root = Path(recorded) if isinstance(recorded, str) and recorded else None
    notes += other_weights(metrics.segmenter_weights, segmenter.weights)
    return RecordedRun(run, adapter, segmenter, vote, settings, scenes, cache_root, notes)


def other_weights(recorded, here: dict[str, str]) -> list[str]:
    """A note where the weights the run recorded (file -> digest) are not the files this
    machine reads for the same setting (another file, or the same name with other bytes): its
    masks, where computed again, come from these."""
    if not isinstance(recorded, dict) or not recorded:
        return []
    theirs = {Path(str(k)).name: v for k, v in recorded.items()}
    ours = {Path(k).name: v for k, v in here.items()}
    differ = sorted(n for n in theirs if ours.get(n) != theirs[n])
    if not differ:
        return []
    return [
        f"the run's segmenter read other weights than this machine's ({', '.join(differ)} "
        "differ or are absent here): masks computed again come from this machine's"
    ]


def _dataset(node: dict) -> DatasetAdapter:
    kind = node.get("kind")
    settings = node.get("adapter")
    if not isinstance(settings, dict):
        raise PluginError("config.dataset.adapter is not an object")
    if kind is None and "_target_" in settings:  # a run from before the registries
        kind = LEGACY_DATASETS.get(str(settings["_target_"]))
        if kind is None:
            raise PluginError(
                f"config.dataset.adapter names the class {settings['_target_']!r}; a run folder "
                "names a registered dataset (`kind`), and no class is built from a file"
            )
        settings = {k: v for k, v in settings.items() if k != "_target_"}
    return DATASETS.build(kind, settings, where="config.dataset.adapter")


def _segmenter_node(node: dict) -> dict[str, Any]:
    if node.get("kind") is None and "_target_" in node:
        kind = LEGACY_SEGMENTERS.get(str(node["_target_"]))
        if kind is None:
            raise PluginError(
                f"config.segmenter names the class {node['_target_']!r}; a run folder names a "
                "registered segmenter (`kind`), and no class is built from a file"
            )
        node = {"kind": kind, **{k: v for k, v in node.items() if k != "_target_"}}
    return node


__all__ = ["RecordedRun", "RunFileError", "read_metrics", "read_recorded_run"]
