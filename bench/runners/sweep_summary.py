"""The table a sweep prints when its last job ends (`hydra.callbacks.sweep_summary` in
conf/eval.yaml): one row per job, the settings that differ between the jobs, and each run's
overall scores, read back from the jobs' metrics.json. `make report` and
`python -m bench.tables.report` build the full tables of the same folders."""

from __future__ import annotations

from pathlib import Path

import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, ListConfig, OmegaConf

from bench.runners.outputs import CACHED_NOTE, fmt
from sagonline.score.run_metrics import METRICS_FILE, MetricsFileError, RunMetrics

# Overrides that change how a run is shown, not what it measures: never a column.
NOT_SETTINGS = ("hydra.", "progress=", "record=", "overwrite=")


def sweep_size(overrides: list[str]) -> int | None:
    """How many jobs the basic sweeper makes of these overrides; None where a value cannot be
    expanded here (`glob(...)` needs the config)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
        size = 1
        for o in parsed:
            if o.is_sweep_override():
                size *= len(list(o.sweep_string_iterator()))
        return size
    except Exception:  # noqa: BLE001 - any syntax Hydra itself accepted but we cannot expand
        return None


def job_folders(sweep_dir: Path, size: int | None = None) -> list[Path]:
    """The sweep's job folders: its sub-folders holding a run's record or log, in job order;
    with `size`, only the numbered ones of this sweep (not those a longer one left)."""
    if not sweep_dir.is_dir():
        return []
    jobs = [
        p
        for p in sweep_dir.iterdir()
        if p.is_dir()
        and not p.name.startswith(".")
        and any((p / name).exists() for name in (METRICS_FILE, "eval.log", ".hydra"))
        and (size is None or not p.name.isdigit() or int(p.name) < size)
    ]
    return sorted(
        jobs, key=lambda p: (not p.name.isdigit(), int(p.name) if p.name.isdigit() else 0, p.name)
    )


def differing_settings(overrides: list[list[str] | None]) -> list[str]:
    """The keys whose value is not the same in every job (a key missing from a job counts as a
    value of its own; a job whose overrides are unknown, None, counts for none), in the order
    they first appear."""
    known = [job for job in overrides if job is not None]
    keys: list[str] = []
    for job in known:
        for item in job:
            key = item.partition("=")[0]
            if not item.startswith(NOT_SETTINGS) and key not in keys:
                keys.append(key)
    values = [dict(item.partition("=")[::2] for item in job) for job in known]
    return [k for k in keys if len({v.get(k) for v in values}) > 1]


def _read(job: Path) -> tuple[RunMetrics | None, str, list[str] | None]:
    """A job's record, its status word and its overrides (from `.hydra/overrides.yaml` where it
    has no readable record; None where neither says them)."""
    try:
        metrics = RunMetrics.of_run(job)
    except MetricsFileError as exc:
        missing = not (job / METRICS_FILE).exists()
        overrides = _overrides_written(job / ".hydra" / "overrides.yaml")
        why = f"no record (failed or cut short: see {job / 'eval.log'})" if missing else str(exc)
        return None, why, overrides
    return metrics, metrics.status or "complete", metrics.overrides


def _overrides_written(path: Path) -> list[str] | None:
    """The overrides a job wrote into `.hydra/` before it stopped; None where unreadable."""
    try:
        written = OmegaConf.load(path) if path.is_file() else None
    except (OSError, ValueError, yaml.YAMLError):
        return None
    return [str(o) for o in written] if isinstance(written, ListConfig) else None


def vote_time(m: RunMetrics) -> str:
    """The run's vote ms a mask (`RunMetrics.vote_ms_per_mask`), one of the stage cache's
    makers marked `*` (CACHED_NOTE)."""
    ms, cached = m.vote_ms_per_mask()
    return fmt(ms, False) + ("*" if cached and ms is not None else "")


def sweep_table(sweep_dir: Path, size: int | None = None) -> str:
    """The sweep in `sweep_dir` (of `size` jobs, where known) as lines of text: a row per job,
    the differing settings as columns, then the job of the highest mIoU and the command that
    tabulates the sweep."""
    jobs = job_folders(sweep_dir, size)
    read = [_read(job) for job in jobs]
    keys = differing_settings([o for _, _, o in read])
    cells = [
        [dict(item.partition("=")[::2] for item in (o or [])).get(k, "-") for k in keys]
        for _, _, o in read
    ]
    widths = [max([len(k), *(len(row[i]) for row in cells)]) + 2 for i, k in enumerate(keys)]
    head = f"{'job':<6}" + "".join(f"{k:<{w}}" for k, w in zip(keys, widths, strict=True))
    lines = [
        f"sweep {sweep_dir}: {len(jobs)} job(s), {sum(r[0] is not None for r in read)} "
        "with a record",
        head + f"{'status':<11}{'mIoU':>8}{'mAcc':>8}{'seg mIoU':>10}{'vote ms/mask':>14}",
    ]
    votes = [vote_time(m) if m else "" for m, _, _ in read]
    for job, (m, status, _), row, vote in zip(jobs, read, cells, votes, strict=True):
        lines.append(
            f"{job.name:<6}"
            + "".join(f"{c:<{w}}" for c, w in zip(row, widths, strict=True))
            + (
                f"{status:<11}{fmt(m.miou):>8}{fmt(m.macc):>8}{fmt(m.segmenter_miou):>10}{vote:>14}"
                if m
                else status
            )
        )
    scored = [
        (m.miou, job, row)
        for job, (m, _, _), row in zip(jobs, read, cells, strict=True)
        if m and m.miou is not None
    ]
    if scored and len({r[0].dataset for r in read if r[0]}) == 1:  # one dataset: comparable
        miou, job, row = max(scored, key=lambda s: s[0])
        settings = " ".join(f"{k}={v}" for k, v in zip(keys, row, strict=True))
        lines.append(
            f"highest mIoU {fmt(miou)}: job {job.name}" + (f" ({settings})" if settings else "")
        )
    if any(vote.endswith("*") for vote in votes):
        lines.append(CACHED_NOTE)
    lines.append(f"its tables: make report ARGS={sweep_dir}")
    return "\n".join(lines)


class SweepSummary(Callback):
    """Prints `sweep_table` of the sweep's folder once every job has ended."""

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        try:
            text = sweep_table(sweep_dir, sweep_size(list(config.hydra.overrides.task)))
        except OSError as exc:  # the jobs' results stand; only their table is lost
            text = f"warning: no table of the sweep {sweep_dir}: {exc}"
        print(text, flush=True)
