"""Facts about the machine a timing ran on."""

from __future__ import annotations

import os


def test_the_load_averages_are_the_kernels_and_need_no_uptime(monkeypatch):
    """The benches print the load before and after their timings: read from the kernel, not by
    starting `uptime`, which a slim system lacks (the bench then died with FileNotFoundError)."""
    from sagonline.core.machine import load_averages

    monkeypatch.setenv("PATH", "")  # no uptime to start
    monkeypatch.setattr(os, "getloadavg", lambda: (0.5, 1.25, 2.0))
    assert load_averages() == "load average: 0.50, 1.25, 2.00"
    monkeypatch.delattr(os, "getloadavg")
    assert load_averages() == "load average: -"
