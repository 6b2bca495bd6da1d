"""The student's answer from the average of its weights (`refine.ema_span`)."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from sagonline.core import store
from sagonline.refine import RefineConfig, RefinementTrainer
from sagonline.refine.weight_average import WeightAverage
from tests.refine.test_refine import _toy, interrupt_at


def test_the_average_is_the_plain_mean_then_an_exponential_one_over_the_span():
    """span 5: each step weighs 2/6, or 1/n while that is larger: the first three steps are
    averaged plainly, the fourth and fifth weigh 1/3; the norm layer's running mean is averaged
    too and its batch counter is the current one."""
    net = nn.Sequential(nn.Linear(2, 1), nn.BatchNorm1d(1))
    average = WeightAverage(net, span=5)
    assert average.steps == 0
    values = [1.0, 4.0, 7.0, 10.0, 13.0]
    for n, value in enumerate(values, start=1):
        with torch.no_grad():
            net[0].bias.fill_(value)
            net[1].running_mean.fill_(-value)
            net[1].num_batches_tracked.fill_(n)
        average.update(net)
    expected = sum(values[:3]) / 3  # 4.0
    for value in values[3:]:
        expected += (value - expected) / 3
    assert average.steps == 5
    assert average.model[0].bias.item() == pytest.approx(expected)  # 8.666...
    assert average.model[1].running_mean.item() == pytest.approx(-expected)
    assert average.model[1].num_batches_tracked.item() == 5
    assert net[0].bias.item() == 13.0  # the model itself untouched
    with pytest.raises(ValueError, match="ema_span=0"):
        WeightAverage(net, span=0)
    with pytest.raises(ValueError, match="ema_span"):
        RefineConfig(ema_span=-1)


@pytest.mark.slow
def test_the_student_answers_from_the_average_and_trains_as_without_it(tmp_path):
    """With ema_span the trained weights are those of a training without it; the average is
    that of the weights after each step, and a training interrupted between checkpoints resumes
    to the same average; the answer comes from the average, `span=0` from the weights."""
    frames, coarse, teacher = _toy(3)
    base = dict(max_steps=5, batch_size=2, crop=32, checkpoint_every=2, patience=1000)
    plain = RefinementTrainer(RefineConfig(**base, ema_span=0), 2, frames, coarse, teacher)
    plain.run()
    assert plain.average is None

    cfg = RefineConfig(**base, ema_span=3)
    whole = RefinementTrainer(cfg, 2, frames, coarse, teacher)
    after_each: list[dict] = []
    fold = whole.average.update
    whole.average.update = lambda model: (
        after_each.append(copy.deepcopy(model.state_dict())),
        fold(model),
    )
    whole.run()
    assert whole.losses == plain.losses
    for name, value in plain.model.state_dict().items():
        assert torch.equal(whole.model.state_dict()[name], value), name
    name = "head.1.bias"
    expected = after_each[0][name].clone()
    for n, state in enumerate(after_each[1:], start=1):
        expected += (state[name] - expected) * max(2 / 4, 1 / (n + 1))
    assert torch.allclose(whole.average.model.state_dict()[name], expected)

    interrupt_at(RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt"), 3)
    resumed = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert resumed.step == 2 and resumed.average.steps == 2
    resumed.run()
    for name, value in whole.average.state_dict().items():
        assert torch.equal(resumed.average.state_dict()[name], value), name

    with torch.no_grad():  # the average says 1 everywhere, the trained weights 0
        resumed.average.model.head[-1].bias.copy_(torch.tensor([-100.0, 100.0]))
        resumed.model.head[-1].bias.copy_(torch.tensor([100.0, -100.0]))
    assert (resumed.predict(frames[0], coarse[0]) == 1).all()
    assert (resumed.predict(frames[0], coarse[0], span=0) == 0).all()
    assert (
        RefinementTrainer(cfg, 2, frames, coarse, teacher).predict(frames[0], coarse[0]).tolist()
        == coarse[0].tolist()
    )  # before its first step: the untrained student


@pytest.mark.slow
def test_with_an_average_the_curve_scores_the_answers_and_the_trained_weights():
    frames, coarse, teacher = _toy(3)
    cfg = RefineConfig(max_steps=4, batch_size=2, crop=32, patience=1000, curve_every=2, ema_span=3)
    trainer = RefinementTrainer(cfg, 2, frames, coarse, teacher)
    trainer.score_now = lambda span=None: float(trainer.step) + (0.5 if span == 0 else 0.0)
    trainer.run()
    assert [(p["step"], p["miou"], p["miou_trained"]) for p in trainer.curve] == [
        (0, 0.0, 0.5),
        (2, 2.0, 2.5),
        (4, 4.0, 4.5),
    ]


@pytest.mark.slow
def test_scored_spans_keep_more_averages_and_leave_the_answers_as_they_were(tmp_path):
    """refine.scored_spans: an average per span, updated at every step, kept across a resume;
    the answers' average and the trained weights are those of a training without them."""
    frames, coarse, teacher = _toy(3)
    base = dict(max_steps=4, batch_size=2, crop=32, checkpoint_every=2, patience=1000)
    answers = RefinementTrainer(RefineConfig(**base, ema_span=3), 2, frames, coarse, teacher)
    answers.run()
    cfg = RefineConfig(**base, ema_span=3, scored_spans=[2, 3, 5])
    whole = RefinementTrainer(cfg, 2, frames, coarse, teacher)
    assert sorted(whole.span_averages) == [2, 5]  # 3 is the answers' own
    whole.run()
    assert whole.losses == answers.losses
    for name, value in answers.average.state_dict().items():
        assert torch.equal(whole.average.state_dict()[name], value), name
    assert whole.span_averages[5].steps == 4
    name = "head.1.bias"
    biases = {span: whole.weights(span).state_dict()[name] for span in (0, 2, 3, 5)}
    for a, b in ((0, 2), (2, 3), (3, 5)):  # from step 3 on, each span weighs its steps apart
        assert not torch.equal(biases[a], biases[b]), (a, b)
    assert torch.equal(
        torch.as_tensor(whole.predict(frames[0], coarse[0])),
        torch.as_tensor(answers.predict(frames[0], coarse[0])),
    )

    interrupt_at(RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt"), 3)
    resumed = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert resumed.step == 2 and resumed.span_averages[2].steps == 2
    resumed.run()
    for span in (2, 5):
        for key, value in whole.span_averages[span].state_dict().items():
            assert torch.equal(resumed.span_averages[span].state_dict()[key], value), (span, key)
    finished = store.load_or_discard(tmp_path / "s.pt", "student checkpoint")
    store.save(tmp_path / "s.pt", {k: v for k, v in finished.items() if k != "averages"})
    older = RefinementTrainer(cfg, 2, frames, coarse, teacher, tmp_path / "s.pt")
    assert older.step == 0  # a checkpoint without the averages by span: trained again

    with pytest.raises(ValueError, match=r"no average over 7 steps .*scored_spans=\[2, 3, 5\]"):
        whole.weights(7)
    for bad in ([0], [4, 4]):
        with pytest.raises(ValueError, match="refine.scored_spans"):
            RefineConfig(scored_spans=bad)
