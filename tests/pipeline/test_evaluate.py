"""The library's dataset evaluation (`sagonline.pipeline.evaluate`): every scene run and scored
in order, a scene that cannot load reported as failed while the others go on, Stage II where a
refinement config is given, the stage cache one folder per scene."""

from __future__ import annotations

from sagonline.datasets.base import DatasetAdapter, DatasetError
from sagonline.datasets.synthetic import load_synthetic
from sagonline.pipeline import PipelineSettings
from sagonline.pipeline.evaluate import evaluate_scenes
from sagonline.segment.oracle import OracleSegmenter
from sagonline.vote.consensus import VoteConfig


class TwoScenes(DatasetAdapter):
    """One small synthetic scene that loads, one that does not."""

    name = "two"

    def __init__(self):
        self.task = load_synthetic(
            layout="forward", num_gaussians=800, width=32, height=24, num_train_views=6
        )[0]

    def scene_names(self) -> list[str]:
        return ["broken", "good"]

    def load_scene(self, scene: str):
        if scene == "broken":
            raise DatasetError("broken: no trained scene")
        return self.task


def test_every_scene_is_reported_in_order_and_a_broken_one_does_not_stop_the_rest(tmp_path):
    said, dataset = [], TwoScenes()
    reports = evaluate_scenes(
        dataset,
        ["broken", "good"],
        OracleSegmenter(),
        VoteConfig(),
        PipelineSettings(progress=False),
        cache_root=tmp_path / "cache",
        warn=said.append,
    )
    assert [r.scene for r in reports] == ["broken", dataset.task.name]
    assert reports[0].status == "failed" and "no trained scene" in reports[0].error
    assert said == ["scene broken skipped: broken: no trained scene"]
    assert reports[1].status == "ok" and reports[1].miou > 0.5
    assert all(r.protocol == "two/default@2" for r in reports)
    assert (tmp_path / "cache" / "good").is_dir() and not (tmp_path / "cache" / "broken").exists()
