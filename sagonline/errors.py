"""Errors shared across the library's rooms, low enough that any of them may raise one.

A stored file the harness wrote is `io.store.StoreError`; a mask that does not fit its view is
`consensus.MaskError`.
"""

from __future__ import annotations


class DatasetError(RuntimeError):
    """A dataset folder is missing pieces or has the wrong layout; says what and where."""


class SceneFileError(ValueError):
    """A scene file is missing, truncated or malformed; the message names the file and field."""


class CameraFileError(ValueError):
    """Camera file missing or malformed; the message names the file."""


__all__ = ["CameraFileError", "DatasetError", "SceneFileError"]
