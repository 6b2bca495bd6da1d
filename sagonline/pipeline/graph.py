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
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import torch

from sagonline.cameras import Camera
from sagonline.gaussians import Gaussians
from sagonline.io import store
from sagonline.provenance import digest_arrays, digest_cameras, digest_gaussians, digest_json

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
    """name, code version (bump it when a change to `compute` changes what it returns: every
    cached entry of this stage and of the stages downstream is then recomputed), the inputs
    dataclass, and `compute(inputs, progress) -> output` (None for a stage that is run by its
    own driver and uses only its key, like the student's background training)."""

    name: str
    version: int
    inputs: type
    compute: Callable[[Any, bool], Any] | None

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
    """`<dir>/<stage>-<key>.store` files (`sagonline.io.store`: arrays and JSON, never a
    pickle, each checked against the digest of its own bytes) written atomically; no dir: no
    caching. A damaged or foreign entry is named, removed and recomputed, never used."""

    def __init__(self, directory: str | Path | None):
        self.dir = Path(directory) if directory is not None else None

    def path(self, stage: str, key: str) -> Path | None:
        return None if self.dir is None else self.dir / f"{stage}-{key}{store.SUFFIX}"

    def load(self, stage: str, key: str):
        path = self.path(stage, key)
        return None if path is None else store.load_or_discard(path, "cache entry")

    def save(self, stage: str, key: str, value) -> None:
        if self.dir is not None:
            store.save(self.path(stage, key), value)


@dataclass
class StageRun:
    """What running one stage did: `computed` or `cached`, and the seconds it took here."""

    status: str
    seconds: float


def run_stage(
    stage: Stage[I, O], inputs: I, cache: StageCache, progress: bool = False
) -> tuple[Output[O], StageRun]:
    """The stage's output from the cache when its key is there, else computed and cached."""
    if stage.compute is None:
        raise TypeError(f"stage {stage.name} is run by its own driver, not by run_stage")
    key = stage.key(inputs)
    start = time.perf_counter()
    value = cache.load(stage.name, key)
    if value is not None:
        return Output(key, value), StageRun("cached", time.perf_counter() - start)
    value = stage.compute(inputs, progress)
    cache.save(stage.name, key, value)
    return Output(key, value), StageRun("computed", time.perf_counter() - start)
