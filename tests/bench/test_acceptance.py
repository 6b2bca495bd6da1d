"""The numbers Stage I must reach on the synthetic presets (slow: full default scenes)."""

from __future__ import annotations

import pytest

from tests.fixtures import compose_config

pytestmark = pytest.mark.slow


def _run(tmp_path, *overrides):
    from bench.runners.eval import evaluate

    cfg = compose_config("eval", *["progress=false", "record=false", *overrides])
    return evaluate(cfg, tmp_path)


def test_clean_oracle_reaches_the_bar_on_both_presets(tmp_path):
    m = _run(tmp_path)
    for scene in m["scenes"]:
        assert scene["labels3d"]["accuracy"] >= 0.99, scene["scene"]
        assert scene["miou"] >= 0.95, scene["scene"]


def test_corrupted_oracle_is_repaired(tmp_path):
    m = _run(tmp_path, "segmenter=oracle_noisy")
    for scene in m["scenes"]:
        assert scene["miou"] > scene["segmenter_miou"], scene["scene"]
