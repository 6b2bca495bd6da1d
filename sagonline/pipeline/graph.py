"""Stages as typed functions, cached under a key derived from their inputs.

A `Stage` is a function from one inputs dataclass to one output. Its cache key is the digest of
the stage's name and version and of *every* field of its inputs (`digest_value`): Gaussians,
cameras, arrays and prompts by their content, settings dataclasses field by field, an upstream
stage's output by that output's own key. Nothing lists a stage's dependencies by hand, so an
input added to an inputs dataclass is part of the key the moment it exists; a field of a type
`digest_value` does not know stops the run instead of being left out.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import torch

from sagonline.core import store
from sagonline.core.provenance import digest_arrays, digest_cameras, digest_gaussians, digest_json
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

I = TypeVar("I")  # noqa: E741 (inputs)
O = TypeVar("O")  # noqa: E741 (output)


@dataclass(frozen=True)
class Output(Generic[O]):
    """A stage's output and the key it was computed (or found in the cache) under; a
    downstream stage's key digests this key, not the value."""

    key: str
    value: O


@dataclass(frozen=True)
class Stage(Generic[I, O]):
    """name, code version (bump it when a change to what computes it changes what it returns:
    every cached entry of this stage and of the stages downstream is then recomputed) and the
    inputs dataclass. Stages are computed by their drivers (Stage I's engine,
    `stage_one.StageOne`; the student's background training, `stage_two`), which look their
    outputs up in a `StageCache` under `key(inputs)` first."""

    name: str
    version: int
    inputs: type

    def key(self, inputs: I) -> str:
        if not isinstance(inputs, self.inputs):
            raise TypeError(f"stage {self.name} takes {self.inputs.__name__}, got {inputs!r}")
        return digest_json(self.name, self.version, digest_value(inputs))


def digest_value(value: Any) -> Any:
    """A JSON-able digest of one input value (see the module docstring)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Output):
        return {"output": value.key}
    if isinstance(value, Gaussians):
        return {"gaussians": digest_gaussians(value)}
    if isinstance(value, Camera):
        return {"cameras": digest_cameras([value])}
    if isinstance(value, (np.ndarray, torch.Tensor)):
        return {"arrays": digest_arrays([value])}
    if callable(getattr(value, "digest", None)):  # Prompt, SegmenterRun: their own content
        return {type(value).__name__: value.digest()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: digest_value(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): digest_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, Camera) for v in value):
            return {"cameras": digest_cameras(value)}
        if value and all(isinstance(v, (np.ndarray, torch.Tensor)) for v in value):
            return {"arrays": digest_arrays(value)}
        return [digest_value(v) for v in value]
    raise TypeError(
        f"no digest rule for {type(value).__name__}: teach sagonline.pipeline.graph.digest_value "
        "how its content is digested before it becomes a stage input"
    )


class StageCache:
    """`<dir>/<stage>-<key>.store` files (`sagonline.core.store`: arrays and JSON, never a
    pickle, each checked against the digest of its own bytes) written atomically; no dir: no
    caching.

    An entry describes itself: its digested payload holds the stage's name, version and key
    beside the value, and a load returns the value only when all three match the request. A
    damaged entry, a foreign file, or a valid entry of another stage or key (copied or renamed
    into place) is named in a warning, removed and recomputed, never used. A folder that cannot
    hold the cache (a file, a link loop, read-only) is named in one warning and the run goes on
    without caching."""

    def __init__(self, directory: str | Path | None, *, writable: bool = True):
        self.dir = Path(directory) if directory is not None else None
        self.writable = writable  # False: read entries only (a folder a file named: export)
        self._warned = False

    def path(self, stage: str, key: str) -> Path | None:
        return None if self.dir is None else self.dir / f"{stage}-{key}{store.SUFFIX}"

    def load(self, stage: Stage, key: str):
        """The cached value of `stage` under `key`, or None (absent, or discarded)."""
        path = self.path(stage.name, key)
        if path is None:
            return None
        try:
            if self.writable:
                entry = store.load_or_discard(path, "cache entry")
            else:
                entry = store.load(path) if path.is_file() else None
        except store.StoreError as exc:  # read-only: named, skipped, never removed
            warnings.warn(f"cache entry unusable, computed again: {exc}", stacklevel=2)
            return None
        except OSError as exc:  # e.g. the folder became unreadable
            self._give_up(exc)
            return None
        if entry is None:
            return None
        expected = {"stage": stage.name, "version": stage.version, "key": key}
        found = (
            {k: entry.get(k) for k in expected}
            if isinstance(entry, dict) and "value" in entry
            else None
        )
        if found == expected:
            return entry["value"]
        warnings.warn(
            f"cache entry unusable, removed and recomputed: {path}: holds "
            f"{found or 'no stage record'}, not {expected}",
            stacklevel=2,
        )
        self._remove(path)
        return None

    def save(self, stage: Stage, key: str, value) -> None:
        path = self.path(stage.name, key)
        if path is None or not self.writable:
            return
        entry = {"stage": stage.name, "version": stage.version, "key": key, "value": value}
        try:
            store.save(path, entry)
        except OSError as exc:
            self._give_up(exc)

    def _remove(self, path: Path) -> None:
        if not self.writable:
            return
        try:
            path.unlink(missing_ok=True)
        except OSError as exc:
            self._give_up(exc)

    def _give_up(self, exc: OSError) -> None:
        """The folder cannot hold the cache: say so once, then run without it."""
        if not self._warned:
            warnings.warn(
                f"stage cache {self.dir} is unusable ({exc.strerror or exc}); this run goes on "
                "without caching (its stages are computed, and nothing is saved)",
                stacklevel=3,
            )
        self._warned = True
        self.dir = None


@dataclass
class StageRun:
    """What running one stage did: `computed` or `cached`, and the seconds it took here."""

    status: str
    seconds: float
