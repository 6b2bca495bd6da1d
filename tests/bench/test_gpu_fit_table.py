"""The first GPU fit's table and what `make gpu-bundle` carries for it: the CPU fit's start
points (where a fit of another recipe of seed 0 reads them) and its figures (the table's CPU
row)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[2]


def _fit(folder: Path, device: str, iterations: int, seconds: float, init: str) -> Path:
    folder.mkdir(parents=True)
    (folder / "fit_config.json").write_text(json.dumps({"device": device, "seed": 0}))
    metrics = {
        "scene": "duck_queen",
        "resolution": [456, 342] if device == "cuda" else [228, 171],
        "iterations": iterations,
        "fit_seconds": seconds,
        "gaussians": 50000,
        "psnr_heldout": 19.5,
        "init": init,
        "stopped": "iterations",
    }
    (folder / "fit_metrics.json").write_text(json.dumps(metrics))
    (folder / "init_points.store").write_bytes(b"points")
    return folder


def test_the_gpu_fit_sits_beside_the_cpu_fit_of_the_same_capture_and_seed(tmp_path):
    gpu = _fit(tmp_path / "gpu", "cuda", 7000, 140.0, "triangulated (1388, cached in gaussians)")
    cpu = _fit(tmp_path / "cpu", "cpu", 3000, 963.9, "triangulated (1388 points)")
    run = tmp_path / "real"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"miou": 0.8812, "device": {"gpu": "H200"}}))
    out = tmp_path / "table" / "gpu_fit.csv"
    subprocess.run(
        [sys.executable, "-m", "bench.tables.gpu_fit", str(gpu), "--runs", f"real={run}"]
        + ["--cpu-fit", str(cpu), "--also", f"fit=paper (first 45 s)={cpu}", "--out", str(out)],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    table = pd.read_csv(out).set_index("fit")
    assert table.loc["gpu", "s per 1k iterations"] == 20.0
    assert table.loc["gpu", "real mIoU"] == 88.12 and table.loc["gpu", "gpu"] == "H200"
    cpu_row = table.loc["cpu (the same capture and seed)"]
    assert cpu_row["s per 1k iterations"] == 321.3 and cpu_row["device"] == "cpu"
    assert pd.isna(cpu_row["real mIoU"])  # scored on the GPU fit only
    assert table.loc["fit=paper (first 45 s)", "gaussians"] == 50000  # a label with "=" in it
    assert "cpu (the same capture and seed)" in out.with_suffix(".md").read_text()


def test_the_bundle_carries_the_cpu_fits_start_points_and_figures(tmp_path, monkeypatch):
    """From the project's overlay (scenes/<dataset>/<scene>/, where fits of a read-only capture
    live), as from the capture's own folder."""
    from sagonline.datasets import fits

    monkeypatch.setattr(fits, "SCENES_ROOT", tmp_path / "scenes")
    spec = importlib.util.spec_from_file_location("bundle", ROOT / "scripts" / "bundle_cpu_fit.py")
    bundle_script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bundle_script)
    data, bundle = tmp_path / "data", tmp_path / "bundle"
    assert bundle_script.bundle_cpu_fit("duck_queen", bundle, data) is None  # no fit: nothing
    fit = _fit(tmp_path / "scenes/duck_queen/duck_queen/gaussians", "cpu", 3000, 963.9, "tri")
    assert bundle_script.bundle_cpu_fit("duck_queen", bundle, data) == fit
    points = bundle / "data" / "duck_queen" / "gaussians" / "init_points.store"
    assert points.read_bytes() == b"points"  # where a fit of another recipe of seed 0 looks
    figures = bundle / "cpu_fit" / "duck_queen"
    assert sorted(p.name for p in figures.iterdir()) == ["fit_config.json", "fit_metrics.json"]
