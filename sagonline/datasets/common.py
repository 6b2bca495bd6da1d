"""Pieces every real-dataset adapter shares: trained scenes, cameras, masks, prompts."""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np

from sagonline.datasets.base import DatasetError
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.io import SceneFileError, read_scene
from sagonline.scene.io.cameras import load_cameras, load_llff
from sagonline.scene.io.images import IMAGE_SUFFIXES, image_size, list_images
from sagonline.scene.io.masks import MAX_LABELS, MaskFileError, read_mask
from sagonline.scene.trajectory import pseudo_temporal_order
from sagonline.segment.prompts import ObjectPrompt, Prompt

TRAINED_SCENE_HELP = (
    "put the trained Gaussian scene at {dir}/{folder}/point_cloud.ply (2DGS or 3DGS layout; "
    "a 3DGS output folder with point_cloud/iteration_*/point_cloud.ply also works), or fit one "
    "with `make scenes{fit}`"
)


SCENES_ROOT = Path(
    os.environ.get("SAGONLINE_SCENES", Path(__file__).resolve().parents[2] / "scenes")
)


def fit_variant(recipe: str | None, seed: int) -> str:
    """The variant name of one draw of a fit recipe: `seed<k>` for a seed other than 0, after
    the recipe's own name where it has one (`<recipe>-seed<k>`); '' for the default recipe's
    seed 0."""
    return "-".join(filter(None, [recipe, f"seed{seed}" if seed else ""]))


def is_variant_name(name: str) -> bool:
    """A fit variant names a folder beside `gaussians/`: letters, digits, '-', '_' and '.',
    never a path ('/', '..', a leading '.')."""
    return bool(re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", name)) and ".." not in name


def fit_folder(variant: str = "") -> str:
    """The folder of a scene's fit: `gaussians`, or `gaussians-<variant>` for another draw of
    the recipe (`seed1`, ...) or another recipe. A variant that is not a plain name
    (`is_variant_name`) is refused: it would read or write outside the scene's folder."""
    if variant and not is_variant_name(variant):
        raise ValueError(
            f"fit variant {variant!r}: a plain name (letters, digits, - _ .), never a path"
        )
    return f"gaussians-{variant}" if variant else "gaussians"


def gaussians_dir(scene_dir: Path, dataset: str | None = None, variant: str = "") -> Path:
    """Where a scene's trained Gaussians live: `<scene>/gaussians/`, or, for data on a
    read-only disk, `scenes/<dataset>/<scene>/gaussians/` in the project (where `make scenes`
    writes when the data folder is not writable); `gaussians-<variant>/` for a variant."""
    own = scene_dir / fit_folder(variant)
    if own.exists() or dataset is None:
        return own
    overlay = SCENES_ROOT / dataset / scene_dir.name / fit_folder(variant)
    return overlay if overlay.exists() else own


def find_trained_scene(scene_dir: Path, dataset: str | None = None, variant: str = "") -> Path:
    """The scene's `point_cloud.ply`: gaussians/point_cloud.ply, or the latest
    gaussians/point_cloud/iteration_*/point_cloud.ply (in `gaussians_dir`)."""
    base = gaussians_dir(scene_dir, dataset, variant)
    direct = base / "point_cloud.ply"
    if direct.is_file():
        return direct
    iterations = sorted(
        base.glob("point_cloud/iteration_*/point_cloud.ply"),
        key=lambda p: int(re.sub(r"\D", "", p.parent.name) or 0),
    )
    if iterations:
        return iterations[-1]
    raise DatasetError(
        f"no trained scene for {scene_dir.name}: expected "
        f"{scene_dir / fit_folder(variant) / 'point_cloud.ply'}; "
        + TRAINED_SCENE_HELP.format(
            dir=scene_dir, folder=fit_folder(variant), fit=fit_args(dataset, variant)
        )
    )


def fit_args(dataset: str | None, variant: str = "") -> str:
    """What to add to `make scenes` to fit this dataset's scene in `variant`'s folder."""
    seed = re.fullmatch(r"seed(\d+)", variant or "")
    args = f"seed={seed.group(1)}" if seed else (f"variant={variant}" if variant else "")
    return (f" DATASET={dataset}" if dataset else "") + (f" ARGS={args}" if args else "")


def fit_record(scene_dir: Path, dataset: str | None = None, variant: str = "") -> dict | None:
    """What `make scenes` recorded about the trained scene (iterations, why it stopped, PSNR),
    or None for a scene it did not fit."""
    import json

    path = find_trained_scene(scene_dir, dataset, variant).parent / "fit_metrics.json"
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    keys = ("iterations", "iterations_planned", "stopped", "psnr_train", "psnr_heldout",
            "psnr_heldout_object", "seed", "scene_digest")  # fmt: skip
    return {k: record[k] for k in keys if k in record} | {"path": str(path)}


def load_trained_scene(
    scene_dir: Path, dataset: str | None = None, drop_nonfinite: bool = False, variant: str = ""
) -> Gaussians:
    """The scene's trained Gaussians; NaN/Inf (or overflowing) rows fail the scene unless
    `drop_nonfinite` (the adapters' `drop_nonfinite` setting) drops them."""
    path = find_trained_scene(scene_dir, dataset, variant)
    try:
        return read_scene(path, drop_nonfinite=drop_nonfinite)
    except SceneFileError as exc:
        raise DatasetError(str(exc)) from exc


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
    """A ground-truth mask as (H, W) int64, through the one mask reader (`io.masks`).

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
            full = cv2.resize(
                (mask == label).astype(np.uint8),
                (round(w * sx), round(h * sy)),
                interpolation=cv2.INTER_NEAREST,
            )
            obj.mask = full.astype(bool)
            objects.append(obj)
    return Prompt(frame=frame, objects=objects)
