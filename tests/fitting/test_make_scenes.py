"""`make scenes` leaves a user's scene alone."""

from __future__ import annotations

import numpy as np

from tests.fixtures import (
    compose_config,
    llff_scene,
    object_mask,
    write_image,
)
from tests.refusals import NAMES


def test_make_scenes_leaves_a_users_scene_alone(tmp_path, capsys):
    from bench.runners.scenes import fit_scene
    from sagonline.datasets.generic import PosedMasksDataset

    cams, sc = llff_scene(tmp_path / "cap", NAMES)  # the user's own trained scene
    ply = tmp_path / "cap" / "gaussians" / "point_cloud.ply"
    before = ply.read_bytes()
    for cam, name in zip(cams, NAMES, strict=True):
        mask = (object_mask(sc, cam) > 0).astype(np.uint8) * 255
        write_image(tmp_path / "cap" / "masks" / f"{name}.png", mask)

    cfg = compose_config("scenes", *["dataset=generic", "progress=false"])
    adapter = PosedMasksDataset(tmp_path / "cap", mask_dir="masks")
    assert fit_scene(cfg, adapter, "cap") == {"scene": "cap", "skipped": True}
    assert "did not write" in capsys.readouterr().err
    assert ply.read_bytes() == before
