"""Scored predictions as files anyone can re-score: label-map PNGs and their digests.

A run writes, beside metrics.json:

    predictions/<scene>/<view>.png           the fused labels rendered (coarse mode), as scored
    predictions_refined/<scene>/<view>.png   the student's (refine=student)
    ground_truth/<scene>/<view>.png          the ground truth they were scored against
    ground_truth/scoring.json                protocol id, resize rule, ignored label

Label maps are single-channel PNGs of label ids (8-bit, or 16-bit where an id exceeds 255), 0 =
background, at the resolution they were scored at. `sagonline score PRED GT` scores any
such pair of folders by this harness's rules; `folder_sha256` is the digest metrics.json holds.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np

from sagonline.core.files import atomic_write, atomic_write_json

SCORING_FILE = "scoring.json"


def view_file(folder: Path, scene: str, view: str) -> Path:
    """<folder>/<scene>/<view>.png, with any '/' of a view name kept as a sub-folder name."""
    return folder / scene / f"{view.replace('/', '__')}.png"


def write_label_map(path: Path, labels: np.ndarray) -> None:
    """(H, W) integer label ids -> a lossless single-channel PNG (written atomically)."""
    labels = np.asarray(labels)
    lo, hi = (int(labels.min()), int(labels.max())) if labels.size else (0, 0)
    if lo < 0 or hi > 65535:
        raise ValueError(f"{path}: label ids must lie in [0, 65535] for a PNG, got [{lo}, {hi}]")
    ok, data = cv2.imencode(".png", labels.astype(np.uint8 if hi <= 255 else np.uint16))
    if not ok:
        raise ValueError(f"{path}: could not encode the label map")
    atomic_write(path, lambda tmp: tmp.write_bytes(data.tobytes()))


def read_label_map(path: Path, max_pixels: int | None = None) -> np.ndarray:
    """A label-map PNG -> (H, W) uint8 or uint16 ids, through the one mask reader (`io.masks`,
    "ids": ids are kept as they are, 8- or 16-bit); a colour or unreadable file, or one of more than
    `max_pixels` pixels (checked before decoding), is a clear error."""
    from sagonline.scene.io.masks import read_mask

    return read_mask(path, "ids", max_labels=1 << 16, max_pixels=max_pixels).labels


def label_maps(folder: Path, pattern: str = "*/*.png") -> list[Path]:
    """The label maps of a run's folder, `<scene>/<view>.png` (pattern "*.png": of one scene's
    folder), sorted: what is scored and digested (a scene folder that is a symbolic link is
    entered like any other)."""
    return sorted(p for p in folder.glob(pattern) if p.is_file())


def folder_sha256(folder: Path, pattern: str = "*/*.png") -> str:
    """SHA-256 over the label maps of `folder` (`label_maps`): relative paths and bytes."""
    digest = hashlib.sha256()
    for path in label_maps(folder, pattern):
        digest.update(path.relative_to(folder).as_posix().encode() + b"\0")
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


def write_scoring_rules(folder: Path, protocol: str | None, resize: str, ignore: int | None):
    """The rules a ground-truth folder is scored by, for `sagonline score` (`nearest`: which
    source pixel a resize reads, scene.io.images.NEAREST_SAMPLING)."""
    rules = {"protocol_id": protocol, "resize": resize, "ignore_label": ignore, "nearest": "centre"}
    atomic_write_json(folder / SCORING_FILE, rules)
