"""What a fit is given: an interrupted overwrite keeps the user's scene; a truncated photograph is
refused."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.fixtures import (
    compose_config,
    llff_scene,
    object_mask,
    write_image,
)
from tests.refusals import NAMES


def _scenes_cfg(*overrides):
    return compose_config(
        "scenes",
        *[
            "dataset=generic",
            "progress=false",
            "fit.iterations=2",
            "fit.init_points=300",
            "fit.init=random",
            "fit.view_clearance=0",
            *overrides,
        ],
    )


def test_interrupted_overwrite_keeps_the_users_scene(tmp_path, capsys):
    from bench.runners.scenes import fit_scene
    from sagonline.core import store
    from sagonline.datasets.generic import PosedMasksDataset

    cams, sc = llff_scene(tmp_path / "cap", NAMES)
    for cam, name in zip(cams, NAMES, strict=True):
        write_image(tmp_path / "cap" / "masks" / f"{name}.png", object_mask(sc, cam) * 255)
    out = tmp_path / "cap" / "gaussians"
    users = (out / "point_cloud.ply").read_bytes()
    # what an overwrite=true fit killed after its first checkpoint leaves behind
    store.save(out / "fit_checkpoint.store", {"config": {}, "step": 1})
    adapter = PosedMasksDataset(tmp_path / "cap", mask_dir="masks")
    assert fit_scene(_scenes_cfg(), adapter, "cap")["skipped"]  # without overwrite: refused
    assert "did not write" in capsys.readouterr().err
    assert (out / "point_cloud.ply").read_bytes() == users
    fit_scene(_scenes_cfg("overwrite=true"), adapter, "cap")
    (backup,) = out.glob("point_cloud.ply.bak-*")
    assert backup.read_bytes() == users
    assert fit_scene(_scenes_cfg(), adapter, "cap")["skipped"]  # ours now: already fitted
    assert "already fitted" in capsys.readouterr().out


def test_a_truncated_photograph_is_refused_by_the_fit(tmp_path):
    from sagonline.scene.io.images import ImageFileError, read_rgb

    photo = tmp_path / "p.jpg"
    cv2.imwrite(str(photo), np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8))
    photo.write_bytes(photo.read_bytes()[:-300])
    with pytest.raises(ImageFileError, match="p.jpg: a damaged or truncated image"):
        read_rgb(photo)
