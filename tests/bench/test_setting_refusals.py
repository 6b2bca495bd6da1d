"""Settings refused before any work, naming the key: out of range, misspelt, of another command, a
dataset name that is a path or a root that is a file."""

from __future__ import annotations

import os

import pytest
import torch

from bench.runners.eval import evaluate
from tests.fixtures import (
    cfg_with,
)
from tests.refusals import error_line, one_error_line, run_python


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("consensus.num_masks=-3", "consensus.num_masks=-3: must be > 0"),
        ("consensus.margin=2", "consensus.margin=2.0: must be a share gap in [0, 1)"),
        ("consensus.eps=1.5", "consensus.eps=1.5"),
        ("refine=student refine.max_steps=-1", "refine.max_steps=-1: must be >= 1"),
        ("refine=student refine.time_budget_s=-1", "refine.time_budget_s=-1.0"),
        ("refine=student refine.pretrained=/nonexistent.pt", "refine.pretrained=/nonexistent.pt"),
    ],
)
@pytest.mark.slow
def test_settings_out_of_bounds_stop_before_any_work(tmp_path, capsys, override, message):
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff", *override.split()), run)
    assert exc.value.code == 2 and not (run / "cache").exists()
    assert message in capsys.readouterr().err


def test_a_dataset_name_that_is_a_path_is_refused(tmp_path):
    code, err, _ = run_python(
        "bench.runners.eval", "dataset.name=../../../x", f"hydra.run.dir={tmp_path}/run"
    )
    assert code == 2
    one_error_line(err, "dataset.name='../../../x'", "not a path")
    assert not (tmp_path / "run").exists()


def test_a_dataset_root_that_is_a_file_and_a_setting_of_another_command(tmp_path):
    (tmp_path / "f").write_text("")
    code, err, _ = run_python(
        "bench.runners.eval",
        "dataset=generic",
        f"dataset.root={tmp_path / 'f'}",
        f"hydra.run.dir={tmp_path}/run",
        "record=false",
    )
    assert code == 2 and "is a file; it names the folder that holds the scenes" in err
    code, err, _ = run_python("bench.runners.eval", "finish=true")
    assert code == 2
    one_error_line(err, "no setting 'finish'", "bench.runners.scenes")
    env = {**os.environ, "SAGONLINE_KERNEL_DIR": str(tmp_path / "f")}
    code, err, _ = run_python(
        "sagonline", "render", "nothing.ply", "--out", "x.png", "--backend", "native", env=env
    )
    assert code == 2 and "a bug" not in err


def test_a_misspelt_key_with_a_plus_is_refused(capsys):
    for override in ("+consensus.epss=0.05", "+segmenter.flickr=0.1", "+dataset.adapter.x=1"):
        with pytest.raises(SystemExit):
            cfg_with(override)
        error_line(capsys, "no such setting")


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("dataset.adapter.forward_single.width=0", "dataset.adapter.forward_single.width=0"),
        ("dataset.adapter.forward_single.width=-5", "dataset.adapter.forward_single.width=-5"),
        ("dataset.adapter.cluttered_360.width=100000", "cluttered_360.width=100000"),
        ("dataset.adapter.forward_single.num_train_views=0", "num_train_views=0"),
        ("dataset.adapter.forward_single.num_gaussians=0", "num_gaussians=0"),
        ("consensus.delta=inf", "consensus.delta=inf"),
        ("consensus.eps=nan", "consensus.eps=nan"),
    ],
)
def test_settings_out_of_range_name_their_key(override, key, capsys):
    with pytest.raises(SystemExit):
        cfg_with(override)
    error_line(capsys, key)


def _fails_before_rendering(tmp_path, *overrides) -> str:
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        evaluate(cfg_with("dataset=synthetic_ff", *overrides), run)
    assert exc.value.code == 2
    assert not (run / "cache").exists()  # nothing was rendered
    return str(exc.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA message")
def test_cuda_without_cuda_fails_before_rendering(tmp_path, capsys):
    _fails_before_rendering(tmp_path, "device=cuda")
    assert "device=cuda: CUDA is not available" in capsys.readouterr().err


def test_mistyped_vote_setting_names_the_key():
    from hydra.errors import ConfigCompositionException

    for override, key in (("consensus.eps=abc", "consensus.eps"), ("consensus.epz=0.1", "epz")):
        with pytest.raises(ConfigCompositionException) as exc:  # at composition, before any work
            cfg_with("dataset=synthetic_ff", override)
        assert key in f"{exc.value} {exc.value.__cause__}", override


def test_unreadable_sam2_checkpoint_fails_before_rendering(tmp_path, capsys):
    pytest.importorskip("sam2")
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()  # importing sam2 initialises Hydra globally
    bad = tmp_path / "sam2.pt"
    bad.write_bytes(b"\x00 not a checkpoint\n" * 200)  # the same bytes every run
    _fails_before_rendering(tmp_path, "segmenter=sam2", f"segmenter.checkpoint={bad}")
    err = capsys.readouterr().err
    assert f"segmenter.checkpoint={bad}" in err and "not a readable PyTorch checkpoint" in err


def test_unreadable_yolo_weights_fail_before_rendering(tmp_path, capsys):
    pytest.importorskip("ultralytics")
    bad = tmp_path / "yolo.pt"
    bad.write_bytes(b"\x00 not a checkpoint\n" * 200)  # the same bytes every run
    _fails_before_rendering(tmp_path, "segmenter=yolo", f"segmenter.weights={bad}")
    assert f"segmenter.weights={bad}" in capsys.readouterr().err


def _checked(schema, argv: list[str]) -> str:
    """check_override_keys' one line for `argv` ('' where it lets them through)."""
    import contextlib
    import io

    from bench.runners.overrides import check_override_keys

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            check_override_keys(schema, argv, "cmd")
        except SystemExit as exc:
            assert exc.code == 2 and err.getvalue().count("\n") == 1, err.getvalue()
    return err.getvalue()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["consensus.epz=0.1"], "consensus.epz: no such setting; did you mean consensus.eps?"),
        (["+segmenter=oracle_noisy", "+segmenter.flickr=0.1"], "did you mean segmenter.flicker?"),
        (
            ["segmenter=minisam", "segmenter.weights=w.onnx"],
            "segmenter.weights: no such setting of segmenter minisam; its settings: advise_after,",
        ),
        (
            ["dataset=mold_cape", "dataset.adapter.expected_photo=3"],
            "did you mean dataset.adapter.expected_photos?",
        ),
        (
            ["dataset.adapter.forward_single.widht=3"],
            "did you mean dataset.adapter.forward_single.width?",
        ),
        (["refine=student", "refine.max_step=3"], "did you mean refine.max_steps?"),
        (["consensus.eps=abc"], "consensus.eps=abc: must be a number"),
        (["seed=x"], "seed=x: must be an integer"),
        (["consensus.num_masks=2.5"], "consensus.num_masks=2.5: must be an integer"),  # int | None
        (["record=maybe"], "record=maybe: must be true or false"),
        (
            ["dataset=mold_cape", "dataset.adapter.exclude_reference=1"],
            "dataset.adapter.exclude_reference=1: must be true or false",
        ),
    ],
)
def test_a_misspelt_nested_key_or_a_number_that_is_none_is_one_line(argv, message):
    """Before Hydra composes (its refusal is several lines and suggests a '+' that is refused
    next): the key, the nearest setting or the node's settings."""
    from bench.runners.config import EvalConfig

    assert message in _checked(EvalConfig, argv)


def test_the_nested_check_lets_every_real_setting_through():
    from bench.runners.config import EvalConfig, ScenesConfig

    fine = [
        "--multirun",
        "hydra/launcher=joblib",
        "hydra.sweep.dir=multirun/x",
        "consensus=flashsplat",
        "consensus.eps=0.01,0.1",
        "consensus.delta=null",
        "consensus.min_votes=3",
        "consensus.num_masks=null",
        "refine.pretrained=/w/student.pt",
        "seed=range(0,3)",
        "refine=student",
        "refine.max_steps=3",
        "renderer.backend=torch",
        "label_render.size=truth",
        "corrupt.flicker=0.1",
        "dataset=mold_cape",
        "dataset.root=/data/mold_cape",
        "dataset.adapter.exclude_reference=True",
        "record=false",
        "segmenter=minisam",
        "segmenter.encoder=/w/encoder.onnx",
        "segmenter.encoder_precision=bf16",
    ]
    assert _checked(EvalConfig, fine) == ""
    # a sweep of segmenters: their settings are Hydra's to check, one composition each
    assert _checked(EvalConfig, ["segmenter=classical,oracle", "segmenter.sigma=2"]) == ""
    assert _checked(ScenesConfig, ["fit.iterations=7000", "dataset=duck_queen"]) == ""
    assert "did you mean fit.iterations?" in _checked(ScenesConfig, ["fit.iteration=3"])
