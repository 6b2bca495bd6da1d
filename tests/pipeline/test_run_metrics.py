"""metrics.json through its schema (`sagonline.score.run_metrics.RunMetrics`): a run's record
written and read back unchanged, older files (no version) read as version 1, newer or broken
ones refused naming the file and the problem, other writers' keys kept."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sagonline.score.run_metrics import METRICS_VERSION, MetricsFileError, RunMetrics

OLD = {"dataset": "d", "segmenter": "oracle", "miou": 0.5, "scenes": [{"scene": "a"}]}


def test_a_record_round_trips_in_its_files_order_with_other_writers_keys(tmp_path):
    data = {**OLD, "renderer_resolved": "native", "macc": 0.75}  # an older writer's own key
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps(data))
    record = RunMetrics.read(path)
    assert record.version == 1 and record.miou == 0.5 and record.macc == 0.75
    assert record.unknown == {"renderer_resolved": "native"}
    assert record.to_json() == data and list(record.to_json()) == list(data)
    assert record.recorded("macc") and not record.recorded("overrides") and record.overrides == []
    fresh = RunMetrics(dataset="d", segmenter="s", miou=0.25)
    written = fresh.to_json()
    assert written["version"] == METRICS_VERSION and list(written)[:3] == [
        "dataset",
        "segmenter",
        "consensus",
    ]
    assert RunMetrics.from_json(written) == fresh


def test_scene_extras_are_asked_by_name():
    record = RunMetrics.from_json(
        {**OLD, "scenes": [{"scene": "a", "extra": {"fit": {"psnr_heldout": 17.5}}}]}
    )
    assert record.scene_extra("fit") == {"psnr_heldout": 17.5}
    assert record.scene_extra("diagnosis") == {}
    assert RunMetrics.from_json({**OLD, "scenes": []}).scene_extra("fit") == {}


@pytest.mark.parametrize(
    ("data", "said"),
    [
        ([1, 2], "holds a list, not a JSON object"),
        ({"dataset": "d"}, "lacks ['segmenter', 'scenes', 'miou']"),
        ({**OLD, "version": METRICS_VERSION + 1}, "newer than this code's"),
        ({**OLD, "version": "2"}, "is not a schema version"),
        ({**OLD, "scenes": {"a": 1}}, "scenes is not a JSON list"),
        ({**OLD, "sha256": "x"}, "sha256 is not a JSON dict"),
    ],
)
def test_what_is_not_a_runs_record_is_refused_naming_the_file(tmp_path, data, said):
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps(data))
    with pytest.raises(MetricsFileError) as exc:
        RunMetrics.read(path)
    assert str(exc.value).startswith(str(path)) and said in str(exc.value)


def test_a_truncated_file_is_refused_naming_it(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps(OLD)[:20])
    with pytest.raises(MetricsFileError, match="unreadable"):
        RunMetrics.read(path)


def test_where_a_run_was_started_is_its_workdir_or_its_cache_root_less_its_cache_dir():
    """`run_from`: the recorded workdir; for an older run its absolute cache_root less its
    relative cache_dir; None where neither tells (no cache, an absolute or foreign cache_dir,
    values of the wrong type)."""

    def started(**fields):
        return RunMetrics(dataset="d", segmenter="s", **fields).run_from()

    shared = {"cache_dir": ".cache/stages"}
    assert started(workdir="/w", cache_root="/x/.cache/stages", config=shared) == Path("/w")
    assert started(cache_root="/x/.cache/stages", config=shared) == Path("/x")
    assert started(cache_root="/x/a/../c", config={"cache_dir": "a/../c"}) == Path("/x")
    assert started(cache_root="/x/runs/r/cache", config={"cache_dir": None}) is None
    assert started(cache_root="/elsewhere/cache", config=shared) is None
    assert started(cache_root="/c", config={"cache_dir": "/c"}) is None
    assert started(workdir=5, cache_root=7, config=shared) is None
