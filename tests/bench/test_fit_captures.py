"""`make fits-captures` (bench.runners.fit_captures): every capture's fits of several seeds, one
command, each fit's outcome in a table."""

from __future__ import annotations

import pytest

from bench.runners import fit_captures
from bench.runners.captures import captures


def test_the_dry_run_lists_one_fit_per_capture_and_seed(capsys):
    fit_captures.main(["--dry-run", "--seeds", "2,0", "variant=aniso", "fit.lambda_aniso=1"])
    lines = capsys.readouterr().out.splitlines()
    want = [
        f"python -m bench.runners.scenes dataset={c} seed={k} progress=false variant=aniso "
        "fit.lambda_aniso=1"
        for c in captures()
        for k in (0, 2)
    ]
    assert lines == want and len(want) == 2 * len(captures()) >= 8
    assert fit_captures.variant_of(["variant=a", "fit.x=1", "variant=b"]) == "b"
    assert fit_captures.variant_of(["fit.x=1"]) is None


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--captures", "nope"], "no such capture: nope; the captures: duck_queen"),
        (["seed=3"], "seed=3: give captures with --captures and seeds with --seeds"),
        (["--seeds", "1,x"], "--seeds '1,x': comma-separated integers"),
        (["--jobs", "0"], "--jobs 0: 1 to"),
    ],
)
def test_bad_arguments_are_refused_naming_them(argv, said, capsys):
    with pytest.raises(SystemExit) as stop:
        fit_captures.main(argv)
    assert stop.value.code == 2 and said in capsys.readouterr().err


def test_a_fit_that_fails_is_named_with_its_log_and_the_batch_fails(tmp_path, capsys):
    """A recipe bench.runners.scenes refuses: every fit fails with its own log and its last line."""
    argv = [
        "--captures",
        "duck_queen",
        "--seeds",
        "0,1",
        "--jobs",
        "2",
        "--logs",
        str(tmp_path),
        "fit.iterations=0",
    ]
    with pytest.raises(SystemExit) as stop:
        fit_captures.main(argv)
    assert stop.value.code == 1
    out = capsys.readouterr().out
    assert "2 fits, 2 at once" in out and out.count("failed: ") == 2, out
    for seed in (0, 1):
        log = (tmp_path / f"duck_queen-seed{seed}.log").read_text()
        assert "fit.iterations=0" in log, log


def test_fits_of_two_seeds_started_in_one_second_get_their_own_run_folders():
    """The seeds of one batch start together: a shared run folder would mix their logs, and a
    refused fit's clean-up would delete it under the other (its log handler then fails)."""
    from hydra import compose, initialize_config_dir

    from bench.runners.config import register_schemas
    from tests.fixtures import CONF

    register_schemas()
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        for seed in (0, 1):
            overrides = ["dataset=duck_queen", f"seed={seed}"]
            cfg = compose("scenes", overrides=overrides, return_hydra_config=True)
            run = cfg.hydra.run.dir
            assert run.startswith("runs/scenes/duck_queen/") and run.endswith(f"-seed{seed}"), run


def test_the_other_vector_width_is_a_variant_of_its_own_and_said_in_the_commands(capsys):
    """--width avx512: the fits run with ATEN_CPU_CAPABILITY=avx512 into the variant avx512
    (or <variant>-avx512): another draw of the recipe, never the AVX2 fit's folder."""
    assert fit_captures.at_width(["fit.x=1"], "avx2") == ["fit.x=1"]
    assert fit_captures.at_width(["fit.x=1"], "avx512") == ["fit.x=1", "variant=avx512"]
    assert fit_captures.at_width(["variant=q", "fit.x=1"], "avx512") == [
        "fit.x=1",
        "variant=q-avx512",
    ]
    fit_captures.main(
        ["--dry-run", "--seeds", "1", "--captures", "duck_queen", "--width", "avx512"]
    )
    assert capsys.readouterr().out.strip() == (
        "ATEN_CPU_CAPABILITY=avx512 python -m bench.runners.scenes dataset=duck_queen seed=1 "
        "progress=false variant=avx512"
    )


def test_a_width_the_cpu_lacks_is_refused(monkeypatch):
    """torch falls back to a narrower width without a word: the fits would be AVX2's draws
    under another name."""
    import subprocess

    monkeypatch.setattr(
        subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 0, "AVX2\n", "")
    )
    with pytest.raises(SystemExit, match="--width avx512: torch's CPU kernels run at AVX2"):
        fit_captures.check_width("avx512")
