"""`python -m bench.runners.every`: each N one cold evaluation of a fitted capture, read into a
table of views segmented, seconds, time to first mask and mIoU."""

from __future__ import annotations

import pandas as pd
import pytest

from bench.runners import captures, every, real
from sagonline.score.run_metrics import RunMetrics


def scene(masks: int, segment_ms: float, ttfm: float) -> dict:
    timings = {"segment_ms_per_frame": segment_ms, "time_to_first_mask_s": ttfm}
    return {"scene": "cap", "vote": {"num_masks": masks}, "timings": timings}


def test_each_n_is_one_cold_run_of_its_own_and_one_row(tmp_path, monkeypatch):
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "cap"})
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): True)
    asked = []

    def run(self, capture, source, seed=0, setting=()):
        asked.append((capture, source, seed, setting))
        n = int(setting[0].rsplit("=", 1)[1])
        views = -(-12 // n)
        return RunMetrics(
            dataset="cap",
            segmenter=source,
            miou=0.9 - 0.01 * n,
            segmenter_miou=0.8,
            protocol_id="cap/exclude-reference@1",
            scenes=[scene(views, 2000.0, 2.5)],
            segmenter_info={"encoder": "/w/encoder.ort", "encoder_sha256": "54e9" * 16},
        )

    monkeypatch.setattr(real.Evaluations, "run", run)
    df = every.main(["--captures", "cap", "--every", "1,4", "--out", str(tmp_path / "out")])
    assert [a[3] for a in asked] == [
        ("dataset.adapter.every=1", "segmenter.embedding_cache=none"),
        ("dataset.adapter.every=4", "segmenter.embedding_cache=none"),
    ]
    assert df["views segmented"].tolist() == [12, 3]
    assert df["segment s"].tolist() == [24.0, 6.0]
    saved = pd.read_csv(tmp_path / "out" / "every.csv")
    assert saved["mIoU"].tolist() == [89.0, 86.0]  # in percent
    page = (tmp_path / "out" / "every.md").read_text()
    assert "dataset.adapter.every=4 segmenter.embedding_cache=none" in page
    assert "hydra.run.dir=multirun/real/cap/sam2_tiny@dataset.adapter.every-4+" in page
    assert "- sam2_tiny's weights (file, sha256): encoder.ort 54e954e954e9\n" in page


def test_an_unknown_capture_and_a_zero_n_are_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "cap"})
    for argv, said in (
        (["--captures", "nope"], "'nope' is not a capture"),
        (["--every", "0"], "--every 0: give whole numbers"),
        (["--every", "a"], "--every a"),
    ):
        with pytest.raises(SystemExit) as exc:
            every.main([*argv, "--out", str(tmp_path)])
        assert exc.value.code == 2 and said in capsys.readouterr().err
