"""Fixtures of the command-line tests: a user's scene folder and a click on its object."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.fixtures import own_scene


@pytest.fixture(scope="module")
def user_scene(tmp_path_factory):
    """A user's scene folder (point_cloud.ply, transforms.json, notes.txt) and a click on its
    object in view 0."""
    folder, scene, cams, gt = own_scene(tmp_path_factory.mktemp("user") / "scene")
    inner = cv2.erode((gt == 1).astype(np.uint8), np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(inner)
    click = f"0:{xs[len(xs) // 2] + 0.5},{ys[len(xs) // 2] + 0.5}"
    return folder, click
