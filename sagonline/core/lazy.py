"""Packages that import each public name from its module when it is first read (PEP 562), so
that a command needing one light module (`sagonline score --help`, `sagonline segment --help`)
does not import PyTorch or OpenCV with the package.

    WHERE = {"read_scene": "ply", ...}   # name -> the module of the package that defines it
    __getattr__ = lazy_names(__name__, WHERE)

with the same imports spelt out under `if TYPE_CHECKING:` for type checkers and readers.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_names(package: str, where: Mapping[str, str]) -> Callable[[str], Any]:
    """The `__getattr__` of `package`: a name of `where` (name -> module of the package) is
    imported from its module on first read and kept in the package; any other name raises
    AttributeError."""

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
