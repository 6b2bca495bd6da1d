"""Captures: one that changed is refused, not regrouped; a photograph that is not an image is
named."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.fixtures import compose_config, llff_scene

NAMES = [f"IMG_{i:04d}" for i in range(6)]


def _capture(root: Path) -> Path:
    """A capture in the layout of the shared ones: images_4/, masks_4/, poses_bounds.npy, and a
    fitted scene."""
    from tests.fixtures import object_mask, write_image

    cams, scene = llff_scene(root / "cap", NAMES)
    for cam in cams:
        write_image(
            root / "cap" / "masks_4" / f"{cam.name}.png",
            (object_mask(scene, cam) > 0).astype(np.uint8) * 255,
        )
    return root / "cap"


def _eval_capture(root: Path, *extra: str):
    from bench.runners.eval import evaluate

    cfg = compose_config(
        "eval",
        "dataset=mold_cape",
        f"dataset.root={root}",
        "dataset.name=cap",
        "record=false",
        "progress=false",
        *extra,
    )
    return evaluate(cfg, root.parent / "run")


@pytest.mark.slow
def test_a_capture_that_changed_is_refused_not_regrouped(tmp_path, capsys):
    """A missing photograph moved views between the photographed and mask-only groups without
    a word; a mask at half size was scored at its own size; a photograph that is not an image
    ended in a traceback."""
    cap = _capture(tmp_path)
    photos = f"dataset.adapter.expected_photos={len(NAMES)}"
    (cap / "images_4" / f"{NAMES[2]}.JPG").unlink()
    with pytest.raises(SystemExit):
        _eval_capture(cap, photos)
    assert "5 photographs of the scene's views, the protocol expects 6" in capsys.readouterr().err
    cv2.imwrite(str(cap / "images_4" / f"{NAMES[2]}.JPG"), np.full((24, 32, 3), 90, np.uint8))
    half = cv2.imread(str(cap / "masks_4" / f"{NAMES[3]}.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(cap / "masks_4" / f"{NAMES[3]}.png"), half[::2, ::2])
    with pytest.raises(SystemExit):
        _eval_capture(cap, photos)
    assert "16x12, but the scene's other masks are 32x24" in capsys.readouterr().err


def test_a_photograph_that_is_not_an_image_is_named(tmp_path):
    from sagonline.datasets.common import scene_cameras
    from sagonline.scene.io.images import ImageFileError

    cap = _capture(tmp_path)
    for p in (cap / "images_4").iterdir():
        p.write_bytes(b"not an image")
    with pytest.raises(ImageFileError, match="IMG_0000.JPG: not a readable image"):
        scene_cameras(cap, "images_4")
