"""Dataset adapters: each turns a folder on disk (or a generator) into `SceneTask`s."""

from sagonline.datasets.base import DatasetError, EvalView, SceneTask

__all__ = ["DatasetError", "EvalView", "SceneTask"]
