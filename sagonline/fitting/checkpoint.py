"""A fit's checkpoint: its raw parameters, optimiser state, losses, counters, densification
statistics and settings, saved atomically (`core.store`) so an interrupted fit resumes."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from sagonline.core import store
from sagonline.fitting.config import FitConfig, as_recorded
from sagonline.fitting.losses import ReadLater

# the counters a checkpoint keeps beside the parameters, with their values before any step
COUNTERS = {"step": 0, "elapsed": 0.0, "finished": False, "carved": 0, "co_pruned": 0, "faded": 0}


def save_checkpoint(fitter, path: Path) -> None:  # fitter: a trainer.SceneFitter
    state = {
        "params": {k: v.detach().cpu() for k, v in fitter.params.items()},
        "optim": fitter.optim.state_dict(),
        "history": fitter.history,
        **{k: getattr(fitter, k) for k in COUNTERS},
        **fitter.strategy.state_dict(),
        "config": asdict(fitter.cfg),
    }
    store.save(path, state)


def resume_checkpoint(fitter, path: Path) -> bool:  # fitter: a trainer.SceneFitter
    """Continue an interrupted fit with the same settings (a setting the checkpoint predates
    counts as its default); False if there is none (or it is damaged or not ours: then it is
    named, removed, and the fit starts over)."""
    state = store.load_or_discard(path, "fit checkpoint")
    if state is None:
        return False
    if as_recorded(state["config"], asdict(FitConfig())) != asdict(fitter.cfg):
        return False
    fitter._set_params({k: v.to(fitter.cfg.device) for k, v in state["params"].items()})
    fitter.optim.load_state_dict(state["optim"])
    fitter.losses = ReadLater(state["history"])
    for name, before in COUNTERS.items():  # one a checkpoint predates: its start
        setattr(fitter, name, state.get(name, before))
    fitter.strategy.load_state_dict(state)
    return True
