"""Pieces every real-dataset adapter shares: cameras, masks, prompts (trained scenes:
`fits.py`)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from sagonline.datasets.base import DatasetError
from sagonline.datasets.fits import gaussians_dir
from sagonline.scene.cameras import Camera
from sagonline.scene.io.cameras import load_cameras, load_llff
from sagonline.scene.io.images import IMAGE_SUFFIXES, image_size, list_images, resize_nearest
from sagonline.scene.io.masks import MAX_LABELS, MaskFileError, read_mask
from sagonline.scene.trajectory import pseudo_temporal_order
from sagonline.segment.prompts import ObjectPrompt, Prompt


def scene_cameras(
    scene_dir: Path,
    image_dir: str | None,
    names: list[str] | None = None,
    dataset: str | None = None,
    variant: str = "",
) -> list[Camera]:
    """Cameras of a scene, sorted by name: the trained scene's `gaussians/cameras.json` when
    present (its frame is the scene's), else the capture's own poses (LLFF poses_bounds.npy,
    transforms.json, or a COLMAP model under sparse/0). Rescaled to the images in `image_dir`."""
    size = None
    if image_dir is not None and (scene_dir / image_dir).is_dir():
        images = list_images(scene_dir / image_dir)
        if images:
            size = image_size(images[0])
    gs_cams = gaussians_dir(scene_dir, dataset, variant) / "cameras.json"
    try:
        if gs_cams.is_file():
            cams = load_cameras(gs_cams)
        elif (scene_dir / "poses_bounds.npy").is_file():
            cams = load_llff(scene_dir, image_dir=image_dir if size else None, names=names)
        else:
            cams = load_cameras(scene_dir)
    except (ValueError, OSError) as exc:
        raise DatasetError(f"cameras of {scene_dir}: {exc}") from exc
    if size is not None:
        cams = [c if (c.width, c.height) == size else c.scaled(*size) for c in cams]
    return pseudo_temporal_order(cams)


def load_mask(
    path: Path, threshold: int = 127, mode: str = "binary", max_labels: int = MAX_LABELS
) -> np.ndarray:
    """A ground-truth mask as (H, W) uint8 or uint16 ids, through the one mask reader (`io.masks`).

    mode "binary": foreground where the mask's channel exceeds `threshold` (a colour mask:
    where any channel does; JPEG masks need this); mode "ids": the file's integer values are
    label ids (single channel or palette), below `max_labels`.
    """
    if mode == "ids":
        return read_mask(path, "ids", max_labels=max_labels).labels
    try:
        return read_mask(path, "binary", threshold=threshold, colour="max").labels
    except MaskFileError as exc:
        if "would read as empty" not in str(exc):
            raise
        raise DatasetError(
            f"{exc}: for 0/1 masks set dataset.adapter.mask_threshold=0 (or label_format=ids)"
        ) from None


def match_by_name(masks: list[Path], names: list[str], where: Path) -> dict[str, Path]:
    """Masks keyed by the view name they belong to (stem, minus a `_mask` suffix)."""
    out = {}
    known = set(names)
    for m in masks:
        stem = re.sub(r"[_-]?mask$", "", m.stem)
        if stem not in known:
            raise DatasetError(
                f"{m}: no view named {stem!r} in {where} (views: {names[0]} ... {names[-1]})"
            )
        out[stem] = m
    return out


def list_masks(folder: Path, exclude: tuple[str, ...] = ()) -> list[Path]:
    if not folder.is_dir():
        raise DatasetError(f"mask folder {folder} not found")
    return sorted(
        p
        for p in folder.iterdir()
        if p.suffix in IMAGE_SUFFIXES and not any(word in p.name.lower() for word in exclude)
    )


def check_mask_size(mask: np.ndarray, camera: Camera, path: Path) -> None:
    """GT masks may be at another resolution than the render, but not another aspect ratio."""
    h, w = mask.shape
    if abs(w / h - camera.width / camera.height) > 0.02:
        raise DatasetError(
            f"{path}: mask is {w}x{h} but its view '{camera.name}' is "
            f"{camera.width}x{camera.height} (different aspect ratio)"
        )


def check_one_mask_size(masks: dict[str, np.ndarray], paths: dict[str, Path]) -> None:
    """A scene's ground-truth masks share one size (a capture's resolution): one of another
    size would be scored at its own, its pixels weighing differently, without a word."""
    from collections import Counter

    sizes = Counter(m.shape for m in masks.values())
    if len(sizes) > 1:
        (h, w), _ = sizes.most_common(1)[0]
        odd = next(n for n, m in masks.items() if m.shape != (h, w))
        oh, ow = masks[odd].shape
        raise DatasetError(
            f"{paths[odd]}: {ow}x{oh}, but the scene's other masks are {w}x{h}: every ground "
            "truth of a scene is scored at one resolution"
        )


def clicks_from_mask(
    mask: np.ndarray,
    label: int,
    count: int,
    rng: np.random.Generator,
    scale: tuple[float, float] = (1.0, 1.0),
) -> ObjectPrompt | None:
    """Seeded positive clicks inside `mask == label`, away from its border; pixel centres
    scaled by `scale` (sx, sy) into the frame the segmenter sees."""
    m = (mask == label).astype(np.uint8)
    if not m.any():
        return None
    inner = cv2.erode(m, np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(inner if inner.any() else m)
    pick = rng.choice(len(xs), size=min(count, len(xs)), replace=False)
    pts = np.stack([(xs[pick] + 0.5) * scale[0], (ys[pick] + 0.5) * scale[1]], 1)
    return ObjectPrompt(label=label, points=pts, point_labels=np.ones(len(pts), np.int64))


def click_prompt(
    mask: np.ndarray,
    frame: int,
    num_labels: int,
    clicks: int,
    seed: int,
    scale: tuple[float, float] = (1.0, 1.0),
) -> Prompt:
    """Seeded random positive clicks on each object of one ground-truth mask."""
    rng = np.random.default_rng(seed)
    objects = []
    for label in range(1, num_labels):
        obj = clicks_from_mask(mask, label, clicks, rng, scale)
        if obj is not None:
            sy, sx = scale[1], scale[0]
            h, w = mask.shape
            obj.mask = resize_nearest(mask == label, (round(h * sy), round(w * sx)))
            objects.append(obj)
    return Prompt(frame=frame, objects=objects)
