"""Errors shared across the library's rooms, low enough that any of them may raise one.

A stored file the harness wrote is `core.store.StoreError`; a mask that does not fit its view is
`vote.masks.MaskError`.
"""

from __future__ import annotations


class DatasetError(RuntimeError):
    """A dataset folder is missing pieces or has the wrong layout; says what and where."""


class SceneFileError(ValueError):
    """A scene file is missing, truncated or malformed; the message names the file and field."""


class CameraFileError(ValueError):
    """Camera file missing or malformed; the message names the file."""


class PromptError(ValueError):
    """A prompt that does not fit the scene's views; says which and why."""


class NativeBuildError(RuntimeError):
    """The C++ rasterizer could not be compiled here (no compiler, no ninja, ...)."""


__all__ = [
    "CameraFileError",
    "DatasetError",
    "NativeBuildError",
    "PromptError",
    "SceneFileError",
]
