"""Stage II: network layout, distillation in the background, checkpoints, answer modes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.refine import (
    DualBranchRefiner,
    RefineConfig,
    RefinementTrainer,
    ResNetEncoder,
    load_imagenet_weights,
)
from sagonline.refine.trainer import coarse_input


@pytest.mark.parametrize(
    "arch,params,last",
    [("resnet18", 11_176_512, (512, 512, 3, 3)), ("resnet50", 23_508_032, (2048, 512, 1, 1))],
)
def test_encoder_matches_torchvision_layout(arch, params, last):
    enc = ResNetEncoder(arch)
    sd = enc.state_dict()
    assert sum(p.numel() for p in enc.parameters()) == params  # torchvision's minus the fc layer
    key = "layer4.1.conv2.weight" if arch == "resnet18" else "layer4.2.conv3.weight"
    assert tuple(sd[key].shape) == last
    assert "layer1.0.downsample.0.weight" in sd or arch == "resnet18"
    try:
        from sagonline.segment.compat import import_torchvision

        tv = import_torchvision()
    except ImportError:
        return
    ref = getattr(tv.models, arch)(weights=None).state_dict()
    ref = {k: v.shape for k, v in ref.items() if not k.startswith("fc.")}
    assert ref == {k: v.shape for k, v in sd.items()}


def test_imagenet_checkpoint_loads_and_bad_one_is_named(tmp_path):
    src = ResNetEncoder("resnet18")
    state = {**src.state_dict(), "fc.weight": torch.zeros(1000, 512), "fc.bias": torch.zeros(1000)}
    torch.save(state, tmp_path / "r18.pth")
    dst = ResNetEncoder("resnet18")
    load_imagenet_weights(dst, tmp_path / "r18.pth")
    assert torch.equal(dst.conv1.weight, src.conv1.weight)
    torch.save({"conv1.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(RuntimeError, match="bad.pth does not fit"):
        load_imagenet_weights(dst, tmp_path / "bad.pth")
    with pytest.raises(FileNotFoundError, match="refine.pretrained"):
        load_imagenet_weights(dst, tmp_path / "missing.pth")


def test_untrained_student_answers_the_coarse_mask():
    net = DualBranchRefiner(3, "resnet18").eval()
    labels = torch.randint(0, 3, (37, 50))
    with torch.no_grad():
        out = net(torch.rand(1, 3, 37, 50), coarse_input(labels, 3)[None])
    assert out.shape == (1, 3, 37, 50)
    assert torch.equal(out[0].argmax(0), labels)


def _toy(n=6, h=40, w=48):
    """The teacher's object is one pixel wider than the coarse one, along an RGB edge."""
    rng = np.random.default_rng(0)
    frames, coarse, teacher = [], [], []
    for _ in range(n):
        x0 = int(rng.integers(5, 20))
        img = np.full((h, w, 3), 40, np.uint8)
        img[10:30, x0 : x0 + 16] = 220
        t = np.zeros((h, w), np.int64)
        t[10:30, x0 : x0 + 16] = 1
        c = np.zeros((h, w), np.int64)
        c[12:28, x0 + 2 : x0 + 14] = 1
        frames.append(img)
        coarse.append(c)
        teacher.append(t)
    return frames, coarse, teacher


@pytest.mark.slow
def test_distillation_lowers_the_loss_in_the_background(tmp_path):
    import threading

    frames, coarse, teacher = _toy()
    cfg = RefineConfig(max_steps=30, batch_size=4, crop=32, lr=3e-3, patience=1000)
    tr = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    batch, threads = tr._batch, set()

    def batch_on_its_thread(gen):
        threads.add(threading.get_ident())
        return batch(gen)

    tr._batch = batch_on_its_thread
    tr.start()
    assert tr.wait(300)
    assert threads and threading.get_ident() not in threads  # trained on a thread of its own
    assert tr.status == "steps" and tr.step == 30
    assert np.mean(tr.losses[-5:]) < 0.7 * np.mean(tr.losses[:5])
    pred = tr.predict(frames[0], coarse[0], span=0)  # 30 steps: the average lags them
    agree = lambda a, b: (a == b).mean()  # noqa: E731
    assert agree(pred, teacher[0]) > agree(coarse[0], teacher[0])


@pytest.mark.slow
def test_checkpoint_resume_and_finished_run(tmp_path):
    frames, coarse, teacher = _toy(3)
    cfg = RefineConfig(max_steps=4, batch_size=2, crop=32, checkpoint_every=2, patience=1000)
    first = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    first.cfg = RefineConfig(**{**cfg.__dict__, "max_steps": 2})  # an interrupted run
    first.run()
    first.cfg = cfg
    first.status = "training"
    first.save()
    resumed = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert resumed.step == 2 and not resumed.done.is_set()
    resumed.run()
    assert resumed.step == 4 and resumed.status == "steps"
    again = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert again.done.is_set() and again.step == 4
    other = RefinementTrainer(
        RefineConfig(max_steps=5, batch_size=2, crop=32),
        2,
        frames,
        coarse,
        teacher,
        tmp_path / "s.pt",
    )
    assert other.step == 0  # a different setting starts over


def interrupt_at(trainer: RefinementTrainer, step: int) -> None:
    """Train until `step`, then stop as a Ctrl-C would (its last checkpoint stays)."""
    batch = trainer._batch

    def interrupted(gen):
        if trainer.step == step:
            raise KeyboardInterrupt
        return batch(gen)

    trainer._batch = interrupted
    with pytest.raises(KeyboardInterrupt):
        trainer.run()


@pytest.mark.slow
def test_a_training_interrupted_between_checkpoints_resumes_to_the_uninterrupted_one(tmp_path):
    """Stopped at step 3 (its checkpoint at 2) and resumed, the student draws the batches of
    steps 2 and 3 that one trained straight through draws, and ends with the same weights."""
    frames, coarse, teacher = _toy(3)
    cfg = RefineConfig(max_steps=5, batch_size=2, crop=32, checkpoint_every=2, patience=1000)
    whole = RefinementTrainer(cfg, 2, frames, coarse, teacher)
    whole.run()

    interrupt_at(RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt"), 3)
    resumed = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert resumed.step == 2
    resumed.run()
    assert resumed.losses == whole.losses and resumed.status == whole.status == "steps"
    for name, value in whole.model.state_dict().items():
        assert torch.equal(resumed.model.state_dict()[name], value), name


@pytest.mark.slow
def test_the_curve_scores_the_student_every_few_steps_and_survives_a_resume(tmp_path):
    """curve_every=2 over 5 steps: points at 0, 2, 4 and 5 (where it stopped), each with the
    smoothed loss of then; the weights are those of a training without the curve; a training
    resumed from step 2 keeps the points it had and adds the rest."""
    frames, coarse, teacher = _toy(3)
    base = dict(max_steps=5, batch_size=2, crop=32, checkpoint_every=2, patience=1000, ema_span=0)
    plain = RefinementTrainer(RefineConfig(**base), 2, frames, coarse, teacher)
    plain.run()
    assert plain.curve == []

    cfg = RefineConfig(**base, curve_every=2)
    scored: list[int] = []

    def scorer(trainer):
        def score_now(span=None):
            scored.append(trainer.step)
            return trainer.step / 10

        return score_now

    with_curve = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    with_curve.score_now = scorer(with_curve)
    interrupt_at(with_curve, 3)
    resumed = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert [p["step"] for p in resumed.curve] == [0, 2]
    resumed.score_now = scorer(resumed)
    resumed.run()
    assert scored == [0, 2, 4, 5]  # step 2 scored once: kept in the checkpoint
    assert [p["step"] for p in resumed.curve] == [0, 2, 4, 5]
    assert [p["miou"] for p in resumed.curve] == [0.0, 0.2, 0.4, 0.5]
    assert resumed.curve[0]["loss"] is None
    assert [p["loss"] for p in resumed.curve[1:]] == [
        pytest.approx(ema) for ema in smoothed(plain.losses, [2, 4, 5])
    ]
    for name, value in plain.model.state_dict().items():
        assert torch.equal(resumed.model.state_dict()[name], value), name
    finished = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert finished.done.is_set() and finished.curve == resumed.curve
    with pytest.raises(ValueError, match="curve_every"):
        RefineConfig(curve_every=-1)


def smoothed(losses: list[float], steps: list[int]) -> list[float]:
    """The plateau rule's moving average of `losses` after each of `steps` steps."""
    ema, out = None, []
    for i, loss in enumerate(losses, start=1):
        ema = loss if ema is None else 0.9 * ema + 0.1 * loss
        if i in steps:
            out.append(ema)
    return out


def test_teacher_label_out_of_range():
    frames, coarse, teacher = _toy(2)
    teacher[1][0, 0] = 5
    with pytest.raises(ValueError, match="label 5"):
        RefinementTrainer(RefineConfig(), 2, frames, coarse, teacher)


@pytest.mark.slow
def test_eval_with_refinement_reports_both_modes(tmp_path):
    import pandas as pd

    from bench.runners.eval import evaluate
    from tests.fixtures import cfg_with

    m = evaluate(
        cfg_with(
            "record=false",
            "dataset=synthetic_ff",
            "refine=student",
            "refine.max_steps=3",
            "refine.batch_size=2",
        ),
        tmp_path,
    )
    scene = m["scenes"][0]
    assert scene["refined_miou"] is not None and m["refined_miou"] == scene["refined_miou"]
    assert scene["extra"]["refine"]["steps"] == 3
    # the paper's Table II modes, each alone and while the student trained
    during = scene["extra"]["refine"]["answers_while_training"]
    assert set(during) == {"coarse", "initial", "refined"} and min(during.values()) >= 1
    modes = {f"{m}_ms_per_frame{s}" for m in during for s in ("", "_training")}
    assert modes | {"refine_train_s"} <= set(scene["timings"])
    # initial mode: the oracle answering the eval views (their own ground truth)
    assert scene["extra"]["initial_mode_miou"] > 0.99
    rows = pd.read_csv(tmp_path / "per_view.csv")
    assert set(rows["mode"]) == {"coarse", "refined"}
    assert list((tmp_path / "cache" / "forward_single").glob("refine-*.store"))


@pytest.mark.slow
def test_a_step_budget_gives_the_same_weights_twice(tmp_path):
    """Bounded by steps (the default), the same seed gives the same student: training depends
    on the seed and the thread count, never on how long a step took (so a loaded machine, which
    only slows the steps down, gets the same student as a quiet one)."""

    frames, coarse, teacher = _toy(4)
    cfg = RefineConfig(max_steps=6, batch_size=2, crop=32, patience=1000)

    def weights():
        tr = RefinementTrainer(cfg, 2, frames, coarse, teacher)
        tr.run()
        assert tr.status == "steps" and tr.step == 6
        return {k: v.clone() for k, v in tr.model.state_dict().items()}

    one, two = weights(), weights()
    assert one.keys() == two.keys()
    assert all(torch.equal(one[k], two[k]) for k in one)


@pytest.mark.slow
def test_a_time_budget_stop_is_said_on_screen(tmp_path, capsys):
    from bench.runners.eval import evaluate
    from tests.fixtures import cfg_with

    cfg = cfg_with(
        "record=false",
        "dataset=synthetic_ff",
        "refine=student",
        "refine.time_budget_s=0.000001",
        "refine.batch_size=2",
    )
    m = evaluate(cfg, tmp_path)  # the run's warnings go to its log and to the console
    assert m["scenes"][0]["extra"]["refine"]["status"] == "time_budget"
    err = capsys.readouterr().err
    assert "the student stopped at step" in err and "its time budget" in err
    assert "it answers from the average of its weights over about 60 steps" in err
    assert "depend on how busy the machine was" in (tmp_path / "eval.log").read_text()


def test_a_lucky_first_batch_does_not_end_training():
    """The old rule took the first batch's loss as the best: noisy losses that never beat it by
    min_delta "converged" at step patience + 1. The plateau counts only after a warm-up."""
    from sagonline.refine.plateau import Plateau

    rng = np.random.default_rng(0)
    losses = [0.30] + list(0.50 - 0.002 * np.arange(300) + rng.normal(0, 0.02, 300))
    plateau = Plateau(patience=60, min_delta=1e-3, warmup=60)
    stop = next(
        (i for i, loss in enumerate(losses) if (plateau.add(loss), plateau.converged)[1]), None
    )
    assert stop is None or stop > 200  # the trend still falls: no "convergence" at step 61
    flat = Plateau(patience=60, min_delta=1e-3, warmup=60)
    for i in range(200):
        flat.add(0.2 + 0.01 * np.sin(i))
        if flat.converged:
            break
    assert flat.converged and 120 <= i < 200 and flat.best_step >= 59


def test_the_student_answers_at_another_size_from_its_scores_drawn_up():
    """`predict(..., size)`: an untrained student answers the coarse mask; at twice the size its
    scores, drawn up bilinearly, give that mask twice as large (no blocky grid of its own)."""
    frames, coarse, teacher = _toy(2)
    tr = RefinementTrainer(RefineConfig(max_steps=1), 2, frames, coarse, teacher)
    h, w = coarse[0].shape
    assert np.array_equal(tr.predict(frames[0], coarse[0]), coarse[0])
    large = tr.predict(frames[0], coarse[0], size=(2 * h, 2 * w))
    assert np.array_equal(large, np.kron(coarse[0], np.ones((2, 2), np.int64)))
    assert tr.predict(frames[0], coarse[0], size=(h, w)).shape == (h, w)
