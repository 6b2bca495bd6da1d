"""Mutated scene, camera and mask files give a clear error or a valid load, never a crash."""

from __future__ import annotations

import json
import random
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from sagonline.datasets.base import DatasetError
from sagonline.datasets.common import load_mask
from sagonline.scene.io import SceneFileError, read_scene, write_ply
from sagonline.scene.io.cameras import CameraFileError, load_cameras
from tests.fixtures import (
    llff_scene,
    random_gaussians,
    write_image,
)
from tests.refusals import (
    NAMES,
)


def mutate(data: bytes, rng: random.Random, header_end: int) -> bytes:
    """Truncation, byte flips (anywhere or in the header), or an edited number in the header."""
    kind = rng.choice(["truncate", "flip", "flip_header", "edit_number", "drop_line"])
    if kind == "truncate":
        return data[: rng.randrange(len(data))]
    out = bytearray(data)
    if kind in ("flip", "flip_header"):
        end = header_end if kind == "flip_header" else len(out)
        for _ in range(rng.randint(1, 8)):
            out[rng.randrange(max(end, 1))] = rng.randrange(256)
        return bytes(out)
    head = data[:header_end].decode("latin-1")
    if kind == "edit_number":
        numbers = list(re.finditer(r"\d+", head))
        if numbers:
            m = rng.choice(numbers)
            new = str(rng.choice([0, 1, 7, 10**6, 10**12, 2**63, int(m.group()) * 3]))
            head = head[: m.start()] + new + head[m.end() :]
    else:
        lines = head.split("\n")
        if len(lines) > 2:
            del lines[rng.randrange(1, len(lines) - 1)]
        head = "\n".join(lines)
    return head.encode("latin-1") + data[header_end:]


def _valid_scene(g) -> bool:
    """What a scene reader returns for good input: finite activated Gaussians."""
    return (
        len(g) > 0
        and bool(torch.isfinite(g.means).all() and torch.isfinite(g.scales).all())
        and bool(((g.opacities >= 0) & (g.opacities <= 1)).all() and (g.scales > 0).all())
        and bool(((g.quats.norm(dim=1) - 1).abs() < 1e-3).all())
    )


def _valid_cameras(cams) -> bool:
    return len(cams) > 0 and all(c.width > 0 and c.height > 0 for c in cams)


def _valid_mask(m) -> bool:
    return m.ndim == 2 and m.dtype == np.int64 and set(np.unique(m).tolist()) <= {0, 1}


def _ply_case(tmp: Path):
    path = write_ply(tmp / "s.ply", random_gaussians(60, kind="2dgs", sh_degree=1))
    return path, path.read_bytes().index(b"end_header") + 11, read_scene, SceneFileError


def _splat_case(tmp: Path):
    rng = np.random.default_rng(0)
    rows = np.zeros(40, [("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)])
    rows["p"], rows["s"] = rng.normal(size=(40, 3)), rng.uniform(0.01, 0.1, (40, 3))
    rows["c"], rows["r"] = 200, [255, 128, 128, 128]
    path = tmp / "s.splat"
    path.write_bytes(rows.tobytes())
    return path, 0, read_scene, SceneFileError


def _transforms_case(tmp: Path):
    frames = [
        {"file_path": f"./v{i}.png", "transform_matrix": np.eye(4).tolist()} for i in range(3)
    ]
    path = tmp / "transforms.json"
    path.write_text(json.dumps({"camera_angle_x": 0.8, "w": 32, "h": 24, "frames": frames}))
    return path, len(path.read_bytes()), load_cameras, CameraFileError


def _poses_case(tmp: Path):
    llff_scene(tmp, NAMES, with_scene=False)
    path = tmp / "poses_bounds.npy"
    return path, path.read_bytes().index(b"\n") + 1, load_cameras, CameraFileError


def _mask_case(tmp: Path):
    path = tmp / "m.png"
    mask = np.zeros((24, 32), np.uint8)
    mask[5:15, 8:20] = 255
    write_image(path, mask)
    return path, 33, load_mask, DatasetError


VALID = {
    "_ply_case": _valid_scene,
    "_splat_case": _valid_scene,
    "_transforms_case": _valid_cameras,
    "_poses_case": _valid_cameras,
    "_mask_case": _valid_mask,
}


@pytest.mark.parametrize(
    "case", [_ply_case, _splat_case, _transforms_case, _poses_case, _mask_case]
)
def test_mutated_files_give_a_clear_error_or_a_valid_load(tmp_path, case):
    path, header_end, load, error = case(tmp_path)
    original = path.read_bytes()
    rng = random.Random(f"{case.__name__}-0")
    outcomes = {"error": 0, "loaded": 0}
    valid = VALID[case.__name__]
    for trial in range(60):
        path.write_bytes(mutate(original, rng, header_end))
        try:
            result = load(path)
        except error as exc:
            assert str(path) in str(exc) or path.name in str(exc), (trial, exc)
            outcomes["error"] += 1
            continue
        assert valid(result), trial  # a valid load: what the reader returns for good input
        outcomes["loaded"] += 1
    assert outcomes["error"] > 0, outcomes
