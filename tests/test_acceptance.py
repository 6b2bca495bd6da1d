"""The numbers Stage I must reach on the synthetic presets (slow: full default scenes)."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.slow


def _run(tmp_path, *overrides):
    from hydra import compose, initialize_config_dir

    from bench.eval import evaluate
    from tests.test_eval_runner import CONF

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("eval", overrides=["progress=false", "record=false", *overrides])
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
