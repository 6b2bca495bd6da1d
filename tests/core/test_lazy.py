"""Packages that import their names on first read (`core.lazy`): each name listed resolves to its
module's own object, the list and the map agree, and no name is shadowed by a module."""

from __future__ import annotations

import importlib
import pkgutil

import pytest

LAZY_PACKAGES = ("sagonline.scene.io", "sagonline.render", "sagonline.segment")


@pytest.mark.parametrize("name", LAZY_PACKAGES)
def test_a_lazy_package_offers_each_name_from_its_module(name):
    package = importlib.import_module(name)
    assert sorted(package.__all__) == sorted(package.WHERE)
    modules = {m.name for m in pkgutil.iter_modules(package.__path__)}
    # a name that is also a module's would be the module once anything imports it
    assert not set(package.WHERE) & modules, set(package.WHERE) & modules
    for attribute, module in package.WHERE.items():
        own = getattr(importlib.import_module(f"{name}.{module}"), attribute)
        assert getattr(package, attribute) is own, attribute
    with pytest.raises(AttributeError, match="no_such_name"):
        package.no_such_name  # noqa: B018
