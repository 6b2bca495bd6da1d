"""The table a sweep prints at its end: its jobs in order, the settings that differ between
them as columns, each job's scores or why it has none, and the job of the highest mIoU."""

from __future__ import annotations

from pathlib import Path

from bench.runners.sweep_summary import differing_settings, sweep_size, sweep_table
from sagonline.core.files import atomic_write_json
from sagonline.score.run_metrics import RunMetrics


def _job(sweep: Path, num: int, overrides: list[str], miou: float | None, status="complete"):
    cached = num == 1  # its vote came from the stage cache: the time of the run that made it
    record = RunMetrics(
        dataset="synthetic",
        segmenter="oracle",
        miou=miou,
        macc=miou,
        segmenter_miou=1.0,
        overrides=overrides,
        status=status,
        timings={} if cached else {"vote_ms_per_mask": 5.25},
        scenes=[{"scene": "a", "cached_timings": {"vote_ms_per_mask": 7.0 + k}} for k in (0, 2)],
    )
    atomic_write_json(sweep / str(num) / "metrics.json", record.to_json())


def test_only_the_settings_that_differ_are_columns():
    jobs = [
        ["consensus.eps=0.01", "dataset=nvos", "record=false"],
        ["consensus.eps=0.1", "dataset=nvos", "record=true", "consensus.delta=3"],
        None,  # a job that wrote nothing: counts for no key
    ]
    assert differing_settings(jobs) == ["consensus.eps", "consensus.delta"]
    assert differing_settings([["a=1"], ["a=1"]]) == []


def test_the_sweep_size_follows_the_basic_sweepers_product():
    assert sweep_size(["consensus.eps=0.01,0.1", "seed=range(0,3)", "dataset=nvos"]) == 6
    assert sweep_size(["seed=1"]) == 1
    assert sweep_size(["segmenter=glob(*)"]) is None  # expands only against the config


def test_the_table_names_every_job_and_the_highest_miou(tmp_path):
    sweep = tmp_path / "sweep"
    _job(sweep, 0, ["consensus.eps=0.01", "progress=false"], 0.8)
    _job(sweep, 1, ["consensus.eps=0.1", "progress=false"], 0.9)
    _job(sweep, 2, ["consensus.eps=0.5", "progress=false"], None, status="failed")
    (sweep / "3").mkdir()
    (sweep / "3" / "metrics.json").write_text('{"dataset": ')  # cut short
    (sweep / "10" / ".hydra").mkdir(parents=True)
    (sweep / "10" / ".hydra" / "overrides.yaml").write_text("- consensus.eps=0.9\n")
    (sweep / "10" / "eval.log").write_text("")  # started, never finished
    (sweep / "cache").mkdir()  # a sweep's stage cache is no job

    lines = sweep_table(sweep).splitlines()
    assert lines[0] == f"sweep {sweep}: 5 job(s), 3 with a record"
    assert lines[1].split() == [
        "job",
        "consensus.eps",
        "status",
        "mIoU",
        "mAcc",
        "seg",
        "mIoU",
        "vote",
        "ms/mask",
    ]
    assert lines[2].split() == ["0", "0.01", "complete", "80.00", "80.00", "100.00", "5.2"]
    assert lines[3].split() == ["1", "0.1", "complete", "90.00", "90.00", "100.00", "8.0*"]
    assert lines[4].split()[:4] == ["2", "0.5", "failed", "-"]
    assert "3/metrics.json: unreadable" in lines[5]
    assert (
        lines[6].split()[:2] == ["10", "0.9"]
        and "no record" in lines[6]
        and "10/eval.log" in lines[6]
    )
    assert lines[7] == "highest mIoU 90.00: job 1 (consensus.eps=0.1)"
    assert lines[8].startswith("* a vote served from the stage cache")
    assert lines[9] == f"its tables: make report ARGS={sweep}"
    # a sweep of 2 jobs into a folder a longer one filled: only its own jobs
    assert sweep_table(sweep, size=2).splitlines()[0] == f"sweep {sweep}: 2 job(s), 2 with a record"


def test_runs_of_other_datasets_name_no_highest_miou(tmp_path):
    _job(tmp_path, 0, ["dataset=nvos"], 0.8)
    _job(tmp_path, 1, ["dataset=mold_cape"], 0.9)
    record = RunMetrics.of_run(tmp_path / "1")
    record.dataset = "mold_cape"
    atomic_write_json(tmp_path / "1" / "metrics.json", record.to_json())
    table = sweep_table(tmp_path)
    assert "highest" not in table and table.splitlines()[2].split()[:2] == ["0", "nvos"]


def test_an_empty_or_missing_sweep_folder_is_a_table_of_no_jobs(tmp_path):
    lines = sweep_table(tmp_path / "none").splitlines()
    assert lines[0].endswith(": 0 job(s), 0 with a record") and "highest" not in "".join(lines)
