"""The fit's threads: torch's own CPU ops on one thread, the compiled kernel on all of them."""

from __future__ import annotations

import functools

import torch


def on_one_torch_thread(method):
    """On the CPU, run a fitter's method with torch's own ops on one thread and the compiled
    kernel on all of torch's threads (`native.torch_on_one_thread`): torch splits large
    elementwise ops and reductions over threads in chunks that round differently, so this is
    what makes the same seed give the same scene on any thread count."""

    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        cfg = getattr(self, "cfg", None) or (args[0] if args else kwargs["cfg"])  # __init__'s
        if torch.device(cfg.device).type != "cpu" or torch.get_num_threads() == 1:
            return method(self, *args, **kwargs)
        from sagonline.render.native import torch_on_one_thread

        with torch_on_one_thread():
            return method(self, *args, **kwargs)

    return wrapped
