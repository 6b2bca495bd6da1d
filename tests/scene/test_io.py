"""Scene files: real layouts, exact round trips, and clear errors on bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from sagonline.scene.io import SceneFileError, read_scene, write_ply
from tests.fixtures import random_gaussians, shared_data

FIELDS = ("means", "quats", "scales", "opacities", "sh")


def _equal(a, b):
    return all(torch.equal(getattr(a, f), getattr(b, f)) for f in FIELDS)


def test_donut_minimal_layout():
    g = read_scene(shared_data("donut_3dgs", "point_cloud.ply"))
    assert len(g) == 45624 and g.kind == "3dgs" and g.sh_degree == 0 and g.normals is None
    assert torch.allclose(g.quats.norm(dim=1), torch.ones(len(g)), atol=1e-6)
    assert (g.opacities > 0).all() and (g.opacities < 1).all() and (g.scales > 0).all()


def test_sh3_full_layout_and_round_trip(tmp_path):
    g = read_scene(shared_data("sh3_scene_3dgs", "point_cloud.ply"))
    assert len(g) == 9080 and g.sh_degree == 3 and g.normals is not None
    h = read_scene(write_ply(tmp_path / "out.ply", g))
    assert _equal(g, h) and torch.equal(g.normals, h.normals)
    # f_rest is channel-major in the file: f_rest_0..14 are the 15 red coefficients.
    raw = PlyData.read(str(shared_data("sh3_scene_3dgs", "point_cloud.ply")))["vertex"]
    assert g.sh[0, 1:, 0].tolist() == pytest.approx([raw[f"f_rest_{i}"][0] for i in range(15)])
    assert g.sh[0, 1:, 1].tolist() == pytest.approx([raw[f"f_rest_{i}"][0] for i in range(15, 30)])


def test_splat_format():
    g = read_scene(shared_data("sh3_scene_3dgs", "model.splat"))
    assert len(g) == 22764 and g.sh_degree == 0
    assert torch.allclose(g.quats.norm(dim=1), torch.ones(len(g)), atol=1e-6)


def test_splat_to_ply_is_within_logit_rounding(tmp_path):
    # u8/255 opacities have no exact float32 logit (one logit step spans several opacity ulps
    # where the sigmoid is flat); everything else is exact.
    g = read_scene(shared_data("sh3_scene_3dgs", "model.splat"))
    h = read_scene(write_ply(tmp_path / "s.ply", g))
    assert all(
        torch.equal(getattr(g, f), getattr(h, f)) for f in ("means", "quats", "scales", "sh")
    )
    assert not torch.equal(g.opacities, h.opacities)
    assert torch.allclose(g.opacities, h.opacities, rtol=1e-6, atol=0)


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_write_read_write_is_stable(tmp_path, kind):
    g = read_scene(write_ply(tmp_path / "a.ply", random_gaussians(500, kind, sh_degree=2)))
    assert g.kind == kind
    assert _equal(g, read_scene(write_ply(tmp_path / "b.ply", g)))


def _write_vertex(path, columns: dict, name="vertex"):
    rec = np.empty(len(next(iter(columns.values()))), dtype=[(k, "f4") for k in columns])
    for k, v in columns.items():
        rec[k] = v
    PlyData([PlyElement.describe(rec, name)]).write(str(path))


def _columns(n=4):
    cols = {
        k: np.zeros(n, np.float32)
        for k in [
            "x",
            "y",
            "z",
            "f_dc_0",
            "f_dc_1",
            "f_dc_2",
            "opacity",
            "scale_0",
            "scale_1",
            "scale_2",
            "rot_0",
            "rot_1",
            "rot_2",
            "rot_3",
        ]
    }
    cols["rot_0"][:] = 1
    return cols


def test_truncated_file(tmp_path):
    src = write_ply(tmp_path / "ok.ply", random_gaussians(50))
    bad = tmp_path / "truncated.ply"
    bad.write_bytes(src.read_bytes()[:-100])
    with pytest.raises(SceneFileError, match="truncated.ply"):
        read_scene(bad)


def test_missing_property(tmp_path):
    cols = _columns()
    del cols["opacity"]
    _write_vertex(tmp_path / "s.ply", cols)
    with pytest.raises(SceneFileError, match=r"s\.ply.*'opacity'"):
        read_scene(tmp_path / "s.ply")


def test_wrong_element_name(tmp_path):
    _write_vertex(tmp_path / "s.ply", _columns(), name="gaussian")
    with pytest.raises(SceneFileError, match="no 'vertex' element"):
        read_scene(tmp_path / "s.ply")


def test_nonfinite_values_error_and_drop(tmp_path):
    cols = _columns(5)
    cols["scale_1"][2] = np.nan
    cols["y"][4] = np.inf
    _write_vertex(tmp_path / "s.ply", cols)
    with pytest.raises(SceneFileError, match=r"s\.ply.*property 'y'.*NaN/Inf"):
        read_scene(tmp_path / "s.ply")
    with pytest.warns(UserWarning, match="dropped 2 of 5"):
        g = read_scene(tmp_path / "s.ply", drop_nonfinite=True)
    assert len(g) == 3


def test_zero_norm_quaternion(tmp_path):
    cols = _columns()
    cols["rot_0"][1] = 0
    _write_vertex(tmp_path / "s.ply", cols)
    with pytest.raises(SceneFileError, match="zero-norm quaternions.*row 1"):
        read_scene(tmp_path / "s.ply")


def test_bad_sh_count(tmp_path):
    cols = _columns()
    for i in range(6):
        cols[f"f_rest_{i}"] = np.zeros(4, np.float32)
    _write_vertex(tmp_path / "s.ply", cols)
    with pytest.raises(SceneFileError, match="f_rest"):
        read_scene(tmp_path / "s.ply")


def test_truncated_splat(tmp_path):
    (tmp_path / "a.splat").write_bytes(b"\0" * 70)
    with pytest.raises(SceneFileError, match=r"a\.splat.*32-byte"):
        read_scene(tmp_path / "a.splat")


def test_missing_file(tmp_path):
    with pytest.raises(SceneFileError, match="not found"):
        read_scene(tmp_path / "nope.ply")


@pytest.mark.parametrize("suffix", [".ply", ".splat"])
def test_a_folder_or_a_device_is_named_as_such_not_as_missing(tmp_path, suffix):
    """`/dev/null` and a folder exist: each is said for what it is (both were "not found")."""
    from sagonline.scene.io.ply import read_ply
    from sagonline.scene.io.splat import read_splat

    read = read_ply if suffix == ".ply" else read_splat
    (tmp_path / f"scene{suffix}").mkdir()
    with pytest.raises(SceneFileError, match=rf"scene\{suffix}: a folder, not a scene file"):
        read(tmp_path / f"scene{suffix}")
    with pytest.raises(SceneFileError, match="/dev/null: not a regular file"):
        read("/dev/null")
