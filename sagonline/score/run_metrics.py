"""metrics.json, typed: what a finished evaluation run records, written and read through one
schema with a version. Reports, tables, `sagonline score`, `sagonline export` and the run
folder's resume check read a run through `RunMetrics`, never by key paths of their own.

Versions: 1, the files written before the schema (no `version` key), read as they are;
2, the schema's first, the same keys plus `version`. A file of a later version is refused
(written by newer code), as is one that is not an object or lacks what every run has.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

METRICS_VERSION = 2
METRICS_FILE = "metrics.json"


class MetricsFileError(ValueError):
    """A metrics.json that cannot be read as a run's record; names the file and the problem."""


@dataclass
class RunMetrics:
    """One run's record. Scores are fractions (0-1), None where nothing was scored; `scenes`
    holds one entry per scene (`SceneReport` without its per-view rows)."""

    dataset: str
    segmenter: str
    consensus: dict = field(default_factory=dict)
    renderer: str | None = None
    protocol_id: str | None = None
    miou: float | None = None
    macc: float | None = None
    segmenter_miou: float | None = None
    refined_miou: float | None = None
    refined_macc: float | None = None
    scenes_scored: int = 0
    scenes_failed: list[str] = field(default_factory=list)
    partial: bool = False
    timings: dict = field(default_factory=dict)
    resize_rule: str | None = None
    device: dict = field(default_factory=dict)
    sha256: dict = field(default_factory=dict)  # of the label-map folders (`sagonline score`)
    scenes: list[dict] = field(default_factory=list)
    config: dict = field(default_factory=dict)
    # provenance: how the run came about
    status: str | None = None
    config_fingerprint: str | None = None
    overrides: list[str] = field(default_factory=list)
    git: dict = field(default_factory=dict)
    stage_versions: dict = field(default_factory=dict)
    backends: dict = field(default_factory=dict)
    segmenter_weights: Any = None
    segmenter_info: dict = field(default_factory=dict)
    protocol: dict = field(default_factory=dict)
    cache_root: str | None = None
    # the folder the run was started in, which its relative paths (dataset roots, weights,
    # cache_dir) are relative to
    workdir: str | None = None
    version: int = METRICS_VERSION
    # keys of another writer that this schema does not know: kept, written back as they were
    unknown: dict = field(default_factory=dict)
    # the keys of the file the record was read from, in its order (None: built here)
    read_keys: list[str] | None = field(default=None, repr=False, compare=False)

    # --- reading --------------------------------------------------------------------------

    @classmethod
    def from_json(cls, data: Any, where: str = METRICS_FILE) -> RunMetrics:
        """The record in a parsed metrics.json; MetricsFileError naming `where` and the key."""
        if not isinstance(data, dict):
            raise MetricsFileError(f"{where}: holds a {type(data).__name__}, not a JSON object")
        missing = [k for k in ("dataset", "segmenter", "scenes", "miou") if k not in data]
        if missing:
            raise MetricsFileError(f"{where}: lacks {missing} (not a finished eval run's record)")
        version = data.get("version", 1)
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise MetricsFileError(f"{where}: version {version!r} is not a schema version")
        if version > METRICS_VERSION:
            raise MetricsFileError(
                f"{where}: version {version}, newer than this code's {METRICS_VERSION}"
            )
        known = {f.name for f in dataclasses.fields(cls)} - {"unknown", "version", "read_keys"}
        values = {k: v for k, v in data.items() if k in known}
        for name, kind in (("scenes", list), ("config", dict), ("sha256", dict)):
            if name in values and not isinstance(values[name], kind):
                raise MetricsFileError(f"{where}: {name} is not a JSON {kind.__name__}")
        unknown = {k: v for k, v in data.items() if k not in known and k != "version"}
        return cls(**values, version=version, unknown=unknown, read_keys=list(data))

    @classmethod
    def read(cls, path: Path) -> RunMetrics:
        """The record in the file `path`; MetricsFileError naming it otherwise."""
        if not Path(path).is_file():
            raise MetricsFileError(f"{path}: no such file (not a finished eval run's record)")
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise MetricsFileError(f"{path}: unreadable ({type(exc).__name__}: {exc})") from None
        return cls.from_json(data, str(path))

    @classmethod
    def of_run(cls, run: Path) -> RunMetrics:
        """The record of the run folder `run`."""
        return cls.read(Path(run) / METRICS_FILE)

    # --- writing --------------------------------------------------------------------------

    def to_json(self) -> dict:
        """The JSON object to write: every field in the schema's order. A record read from a
        file gives that file back: its keys in its order (the fields' values as they are now,
        other writers' keys as they were), and a field it lacked only where it was set since."""
        fields = [f for f in dataclasses.fields(self) if f.name not in ("unknown", "read_keys")]
        values = {f.name: getattr(self, f.name) for f in fields}
        written = self.read_keys
        if written is None:
            return values | self.unknown
        out = {k: values[k] if k in values else self.unknown[k] for k in written}
        defaults = RunMetrics(dataset=self.dataset, segmenter=self.segmenter)
        for f in fields:
            if (
                f.name not in out
                and f.name != "version"
                and values[f.name] != getattr(defaults, f.name)
            ):
                out[f.name] = values[f.name]
        return out | {k: v for k, v in self.unknown.items() if k not in out}

    # --- what readers ask ---------------------------------------------------------------

    def recorded(self, key: str) -> bool:
        """Whether the file this record was read from holds `key` (a run older than a field
        lacks it; a record built here holds every field)."""
        return key in self.read_keys if self.read_keys is not None else True

    def first_scene(self) -> dict:
        """The first scene's entry ({} for a run without scenes)."""
        return self.scenes[0] if self.scenes and isinstance(self.scenes[0], dict) else {}

    def vote_ms_per_mask(self) -> tuple[float | None, bool]:
        """The run's vote time, ms a mask, and whether it is the stage cache's: this run's own
        time (False); else, where its scenes' votes were served from the stage cache, the mean
        time of the runs that filled it (True); else (None, False)."""
        if self.timings.get("vote_ms_per_mask") is not None:
            return float(self.timings["vote_ms_per_mask"]), False
        cached = [
            float(s["cached_timings"]["vote_ms_per_mask"])
            for s in self.scenes
            if isinstance(s, dict)
            and (s.get("cached_timings") or {}).get("vote_ms_per_mask") is not None
        ]
        return (sum(cached) / len(cached), True) if cached else (None, False)

    def run_from(self) -> Path | None:
        """The folder the run was started in (`workdir`); for a run that did not record it,
        the one its absolute `cache_root` less its relative `cache_dir` names; else None."""
        if isinstance(self.workdir, str) and self.workdir:  # another writer's value: ignored
            return Path(self.workdir)
        relative = self.config.get("cache_dir")
        if not (isinstance(self.cache_root, str) and isinstance(relative, str) and relative):
            return None
        root, parts = Path(self.cache_root), Path(relative).parts
        if Path(relative).is_absolute() or root.parts[-len(parts) :] != parts:
            return None
        return root.parents[len(parts) - 1]

    def scene_extra(self, key: str) -> dict:
        """The first scene's `extra[key]` ({} where absent): its `diagnosis`, `fit`, ..."""
        return (self.first_scene().get("extra") or {}).get(key) or {}


__all__ = ["METRICS_FILE", "METRICS_VERSION", "MetricsFileError", "RunMetrics"]
