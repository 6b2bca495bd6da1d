"""Image folders and label maps as they are read: which files are images, and nearest-neighbour
resizing of label maps (labels are never interpolated)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")


def list_images(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    return sorted(p for p in folder.iterdir() if p.suffix in IMAGE_SUFFIXES)


def resize_nearest(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) label map -> `shape` by nearest neighbour, dtype kept."""
    if mask.shape == shape:
        return mask
    return cv2.resize(
        mask.astype(np.int32), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST
    ).astype(mask.dtype)
