"""Ground-truth label maps, one reader per format (`label_format` of the posed-masks adapter).

- "binary": foreground where a channel exceeds `threshold` (also JPEG masks);
- "ids": single-channel integer ids (instance or semantic), 0 = background, `ignore` skipped;
- "palette": RGB colours mapped to ids by a palette (e.g. UDD);
- "per_object": `<mask_dir>/<view>/<object>.png`, one binary mask per object (e.g. LERF-Mask);
  object names become label names in sorted order;
- "kitti360": KITTI-360 instance maps (uint16 semanticId * 1000 + instanceId); instances of
  `keep_classes` (Cityscapes ids; vehicles by default) are renumbered 1..K per scene, in order
  of their global id, so one vehicle keeps one label across the sequence.

A reader reads one view's map (`read`), then names the scene's labels from all of them
(`finish`: the maps, possibly renumbered, and the label names, background first).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sagonline.core.errors import DatasetError
from sagonline.datasets.common import load_mask
from sagonline.scene.io.images import IMAGE_SUFFIXES

KITTI360_VEHICLES = (26, 27, 28, 29, 30, 31)  # car truck bus caravan trailer train

Maps = dict[str, np.ndarray]  # view name -> (H, W) label map of non-negative integer ids


@dataclass
class BinaryLabels:
    threshold: int = 127

    def read(self, path: Path) -> np.ndarray:
        return load_mask(path, self.threshold, "binary")

    def finish(self, maps: Maps, mask_root: Path) -> tuple[Maps, list[str]]:
        return maps, ["background", "object"]


@dataclass
class IdLabels:
    names: list[str] | None = None  # the label names, background first; None: "1", "2", ...
    ignore: int | None = None

    def read(self, path: Path) -> np.ndarray:
        return load_mask(path, mode="ids")

    def finish(self, maps: Maps, mask_root: Path) -> tuple[Maps, list[str]]:
        if self.names:
            return maps, list(self.names)
        top = max(
            int(g[g != self.ignore].max(initial=0)) if self.ignore is not None else int(g.max())
            for g in maps.values()
        )
        return maps, ["background"] + [str(i) for i in range(1, top + 1)]


@dataclass
class PaletteLabels(IdLabels):
    palette: dict = field(default_factory=dict)  # "r,g,b" or (r, g, b) -> label id

    def __post_init__(self) -> None:
        self.palette = {
            tuple(int(c) for c in k.split(",")) if isinstance(k, str) else tuple(k): v
            for k, v in self.palette.items()
        }

    def read(self, path: Path) -> np.ndarray:  # [H, W] uint8, uint16 past 255 ids
        """The label map of a colour-coded mask, at the narrowest width its palette's ids need
        (as `io.masks` reads id maps); a colour outside the palette is refused naming it."""
        from sagonline.scene.io.masks import read_mask_colours

        rgb = read_mask_colours(path)
        key = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8)
        key |= rgb[..., 2]
        ids = list(self.palette.values()) or [0]
        wide = min(ids) < 0 or max(ids) > 65535
        out = np.zeros(key.shape, np.int64 if wide else np.uint8 if max(ids) < 256 else np.uint16)
        known = np.zeros(key.shape, bool)
        for color, label in self.palette.items():
            hit = key == ((color[0] << 16) | (color[1] << 8) | color[2])
            out[hit] = label
            known |= hit
        if not known.all():
            bad = rgb[~known][0]
            raise DatasetError(
                f"{path}: colour {tuple(int(v) for v in bad)} is not in the dataset palette"
            )
        return out


@dataclass
class PerObjectLabels:
    threshold: int = 127

    def read(self, path: Path) -> np.ndarray:
        parts = sorted(p for p in path.iterdir() if p.suffix in IMAGE_SUFFIXES)
        if not parts:
            raise DatasetError(f"{path}: no per-object masks")
        names = object_names(path.parent)
        out = None
        for p in parts:
            m = load_mask(p, self.threshold)
            if out is None:  # ids 1..len(names): the narrowest type that holds them
                out = np.zeros(m.shape, np.uint8 if len(names) < 256 else np.uint16)
            out[m > 0] = names.index(p.stem) + 1
        return out

    def finish(self, maps: Maps, mask_root: Path) -> tuple[Maps, list[str]]:
        return maps, ["background", *object_names(mask_root)]


@dataclass
class Kitti360Labels:
    keep_classes: tuple[int, ...] = KITTI360_VEHICLES

    def read(self, path: Path) -> np.ndarray:
        raw = load_mask(path, mode="ids", max_labels=1 << 16)  # semanticId * 1000 + instanceId
        return np.where(np.isin(raw // 1000, self.keep_classes), raw, 0)

    def finish(self, maps: Maps, mask_root: Path) -> tuple[Maps, list[str]]:
        """Global instance codes -> 1..K, one mapping for the whole scene."""
        codes = sorted({int(v) for g in maps.values() for v in np.unique(g) if v != 0})
        lut = {c: i + 1 for i, c in enumerate(codes)}
        out = {}
        for name, g in maps.items():
            r = np.zeros_like(g)
            for c, i in lut.items():
                r[g == c] = i
            out[name] = r
        return out, ["background"] + [f"instance_{c}" for c in codes]


def object_names(mask_root: Path) -> list[str]:
    """Per-object masks: the object names found under any view's folder, sorted."""
    return sorted(
        {
            p.stem
            for d in mask_root.iterdir()
            if d.is_dir()
            for p in d.iterdir()
            if p.suffix in IMAGE_SUFFIXES
        }
    )


LABEL_FORMATS = ("binary", "ids", "palette", "per_object", "kitti360")


def label_reader(
    label_format: str,
    *,
    threshold: int = 127,
    names: list[str] | None = None,
    ignore: int | None = None,
    palette: dict | None = None,
    keep_classes: tuple[int, ...] = KITTI360_VEHICLES,
):
    """The reader of one format, with the settings that format uses."""
    readers = {
        "binary": lambda: BinaryLabels(threshold),
        "ids": lambda: IdLabels(names, ignore),
        "palette": lambda: PaletteLabels(names, ignore, dict(palette or {})),
        "per_object": lambda: PerObjectLabels(threshold),
        "kitti360": lambda: Kitti360Labels(tuple(keep_classes)),
    }
    if label_format not in readers:
        raise DatasetError(f"label_format {label_format!r} is not one of {LABEL_FORMATS}")
    return readers[label_format]()
