"""Scene files: log scales that overflow, NaN hints, and the memory a PLY read takes."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from sagonline.scene.io import SceneFileError, read_scene, write_ply
from tests.fixtures import (
    random_gaussians,
)
from tests.refusals import (
    eval_generic,
    generic_capture,
)


def test_overflowing_log_scale_is_refused_like_nan(tmp_path):
    g = random_gaussians(20)
    path = write_ply(tmp_path / "s.ply", g)
    text = path.read_bytes()
    header_end = text.index(b"end_header\n") + len(b"end_header\n")
    data = np.frombuffer(text[header_end:], dtype=np.float32).copy().reshape(20, -1)
    props = [ln.split()[-1] for ln in text[:header_end].decode().splitlines() if "property" in ln]
    data[7, props.index("scale_1")] = 100.0  # finite in the file, inf after exp
    path.write_bytes(text[:header_end] + data.tobytes())
    with pytest.raises(SceneFileError, match=r"'scale_1'.*overflow.*row 7.*drop_nonfinite=true"):
        read_scene(path)
    with pytest.warns(UserWarning, match="dropped 1 of 20"):
        assert len(read_scene(path, drop_nonfinite=True)) == 19


def test_nan_hint_is_an_eval_setting(tmp_path, capsys):
    root = generic_capture(tmp_path / "cap")
    ply = root / "gaussians" / "point_cloud.ply"
    g = read_scene(ply)
    g.means[3, 0] = float("nan")
    write_ply(ply, g)
    with pytest.raises(SystemExit):
        eval_generic(tmp_path, tmp_path / "run")
    assert "dataset.adapter.drop_nonfinite=true" in capsys.readouterr().err
    metrics = eval_generic(tmp_path, tmp_path / "run2", "dataset.adapter.drop_nonfinite=true")
    assert metrics["scenes_scored"] == 1


def test_reading_a_ply_peaks_below_one_and_a_half_times_its_size(tmp_path, monkeypatch):
    from sagonline.scene.io import ply_rows

    path = write_ply(tmp_path / "big.ply", random_gaussians(40_000, sh_degree=3))
    monkeypatch.setattr(ply_rows, "BLOCK_ROWS", 2048)
    tracemalloc.start()
    g = read_scene(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(g) == 40_000
    assert peak <= 1.5 * path.stat().st_size, peak / path.stat().st_size
