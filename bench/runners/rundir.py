"""Run directories: finished runs are never rewritten, sweeps resume, reports read them.

A run directory holds one finished run once its metrics.json says so. Rerunning into it with
the same config (presentation keys aside) and the same inputs skips it (saying so where it was
made at another commit); another config or changed inputs are refused naming the difference,
and nothing in the folder changes.
"""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import asdict
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from sagonline.core.files import atomic_write_text
from sagonline.core.provenance import digest_json
from sagonline.score.run_metrics import METRICS_FILE, MetricsFileError, RunMetrics


class RunExists(SystemExit):
    """A finished run is in the way: refused, nothing of it was touched."""


# Settings that change how a run is shown or stored, never its numbers: a finished run with
# other values of these is still the same run.
PRESENTATION_KEYS = ("overwrite", "progress", "record", "cache", "cache_dir", "threads", "diagnose")


# Settings added after runs were made, with the value that does what those runs did: a
# finished run whose config lacks one is compared as if it had that value (a new option left
# at its default does not make a finished run "another config"). A plug-in's own setting
# counts only where this run's plug-in has it (the SAM family's segmenter.max_growth).
ADDED_SETTINGS = {
    "consensus.body": False,
    "consensus.weighting": "count",
    "label_render.size": "render",
    "refine.curve_every": 0,
    "refine.ema_span": 0,
    "refine.scored_spans": [],
    "segmenter.max_growth": None,
}


def comparable_config(config: dict) -> dict:
    """A resolved config as flat `a.b.c: value` pairs, without PRESENTATION_KEYS."""
    return flatten({k: v for k, v in config.items() if k not in PRESENTATION_KEYS and k != "hydra"})


def finished_config(config: dict, now: dict) -> dict:
    """A finished run's recorded config made comparable (`comparable_config`), the settings
    added since that this run's flat config `now` has at the values that do what it did
    (ADDED_SETTINGS)."""
    flat = comparable_config(config)
    if flat:
        for key, value in ADDED_SETTINGS.items():
            if key in now:
                flat.setdefault(key, value)
    return flat


def config_fingerprint(cfg) -> tuple[str, dict]:
    """Digest of the resolved config (an EvalConfig) without PRESENTATION_KEYS, and the flat
    dict it hashes."""
    flat = comparable_config(asdict(cfg))
    return digest_json(flat), flat


def flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def read_run_metrics(path: Path) -> RunMetrics | None:
    """A run's metrics.json for reports and tables, or None (with a warning naming the file and
    the problem) when it is unreadable, truncated, or not a run's record (`RunMetrics`): one
    bad run never aborts a report, nor becomes a silent row of blanks."""
    try:
        return RunMetrics.read(path)
    except MetricsFileError as exc:
        print(f"warning: skipped {exc}", file=sys.stderr)
        return None


def finished_run(out_dir: Path) -> RunMetrics | None:
    """The record of a finished run in `out_dir` (one that scored at least one scene), else
    None: no run, an interrupted one, or one whose every scene failed (rerun freely). A record
    that cannot be read stops, naming it."""
    path = out_dir / METRICS_FILE
    if not path.is_file():
        return None
    try:
        metrics = RunMetrics.read(path)
    except MetricsFileError as exc:
        print(f"error: {exc}; move it away or pass overwrite=true", file=sys.stderr)
        raise RunExists(2) from None
    return None if metrics.status == "failed" else metrics


def code_difference(previous: RunMetrics, now_git: dict, now_stages: dict) -> str:
    """How the code that made `previous` differs from this checkout's (`git_state()` and
    `STAGE_VERSIONS`), as a clause; '' where nothing recorded differs."""
    then = (previous.git or {}).get("commit")
    now = now_git.get("commit")
    if not then or not now or then == now:
        return ""
    stages = [
        f"{name} {previous.stage_versions.get(name, '<absent>')} -> {version}"
        for name, version in now_stages.items()
        if previous.stage_versions and previous.stage_versions.get(name) != version
    ]
    return (
        f"made at commit {then[:10]}, this checkout is {now[:10]}"
        + (f" (stage versions {', '.join(stages)})" if stages else "")
        + ": its numbers are that code's; overwrite=true reruns it (unchanged stages come "
        "from the cache)"
    )


def config_difference(old: dict, new: dict, limit: int = 8) -> list[str]:
    """Lines `key: finished-run value -> this run's value` for every key that differs."""
    keys = sorted(set(old) | set(new))
    missing = "<absent>"
    lines = [
        f"  {k}: {old.get(k, missing)!r} -> {new.get(k, missing)!r}"
        for k in keys
        if old.get(k, missing) != new.get(k, missing)
    ]
    return lines[:limit] + ([f"  ... and {len(lines) - limit} more"] if len(lines) > limit else [])


def refuse(out_dir: Path, why: list[str]) -> None:
    print(
        "\n".join(
            [f"error: {out_dir} already holds a finished run (metrics.json) {why[0]}", *why[1:]]
            + [
                "  Nothing was changed. Choose another hydra.run.dir / hydra.sweep.dir, or pass "
                "overwrite=true to replace it."
            ]
        ),
        file=sys.stderr,
    )
    raise RunExists(2)


def write_hydra_files(out_dir: Path, cfg) -> list[str]:
    """`.hydra/{config,hydra,overrides}.yaml` of this run, written by us once the run is
    allowed to proceed (Hydra's own copy is off: `hydra.output_subdir: null`), so a refused
    rerun never rewrites a finished run's record. Returns the command-line overrides."""
    from hydra.core.hydra_config import HydraConfig

    try:
        hydra_cfg = HydraConfig.get()
    except ValueError:  # composed directly (tests): no Hydra job
        return []
    overrides = list(hydra_cfg.overrides.task)
    atomic_write_text(
        out_dir / ".hydra" / "config.yaml", OmegaConf.to_yaml(OmegaConf.structured(cfg))
    )
    atomic_write_text(out_dir / ".hydra" / "hydra.yaml", OmegaConf.to_yaml({"hydra": hydra_cfg}))
    atomic_write_text(out_dir / ".hydra" / "overrides.yaml", OmegaConf.to_yaml(overrides))
    return overrides


class SweepGuard(Callback):
    """Refuses a sweep into a folder whose `multirun.yaml` records other overrides (before
    Hydra rewrites it), unless overwrite=true. The same sweep again resumes: its finished
    jobs are skipped by `evaluate`."""

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        recorded = Path(str(config.hydra.sweep.dir)) / "multirun.yaml"
        if not recorded.is_file() or config.get("overwrite"):
            return
        old = list(OmegaConf.load(recorded).hydra.overrides.task)
        new = list(config.hydra.overrides.task)
        if old != new:
            print(
                f"error: {recorded.parent} holds a sweep with other overrides:\n"
                f"  finished: {' '.join(old)}\n  this one: {' '.join(new)}\n"
                "  Nothing was changed. Choose another hydra.sweep.dir, or pass overwrite=true.",
                file=sys.stderr,
            )
            raise RunExists(2)


# What a run writes into its folder: overwrite=true replaces these and nothing else (its own
# stage cache, keyed by content, and the lock stay; a file of the user's is never touched).
RUN_OUTPUTS = (
    "metrics.json",
    "per_view.csv",
    "eval.log",
    ".hydra",
    "recording.rrd",
    "predictions",
    "predictions_refined",
    "ground_truth",
)


def staging_of(out_dir: Path) -> Path:
    """Where a run that replaces a finished one is written until it is complete."""
    return out_dir.parent / f".{out_dir.name}.new-{os.getpid()}"


def _written_by_us(p: Path) -> bool:
    """A run's outputs (RUN_OUTPUTS) and folders the harness wrote into it (their manifests)."""
    from sagonline.core.outputs import is_ours

    if p.name in RUN_OUTPUTS or (p.is_dir() and is_ours(p)):
        return True
    entries = list(p.iterdir()) if p.is_dir() else []
    return bool(entries) and all(e.is_dir() and is_ours(e) for e in entries)


def _move_outputs(src: Path, dst: Path, metrics_first: bool) -> None:
    """Move the run outputs of `src` into `dst`: metrics.json first out of a run, last into
    one, so a folder holding metrics.json holds a whole run whenever the move is cut short."""
    dst.mkdir(parents=True, exist_ok=True)
    moved = sorted(
        (p for p in src.iterdir() if _written_by_us(p)),
        key=lambda p: (p.name == "metrics.json") != metrics_first,
    )
    for p in moved:
        target = dst / p.name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
        p.rename(target)


def swap_in(out_dir: Path, staging: Path) -> None:
    """A complete new run in `staging` takes the place of the finished one in `out_dir`: the old
    outputs go aside, the new ones in, the old ones are deleted. What the harness did not write
    (a file of the user's) stays where it is, and is named."""
    kept = sorted(
        p.name
        for p in out_dir.iterdir()
        if not _written_by_us(p) and p.name not in (".lock", "cache")
    )
    if kept:
        print(
            f"note: {out_dir}: kept what the harness did not write: {', '.join(kept)}",
            file=sys.stderr,
        )
    aside = out_dir.parent / f".{out_dir.name}.replaced-{os.getpid()}"
    _move_outputs(out_dir, aside, metrics_first=True)
    _move_outputs(staging, out_dir, metrics_first=False)
    shutil.rmtree(aside, ignore_errors=True)
    shutil.rmtree(staging, ignore_errors=True)


def recover_interrupted(out_dir: Path) -> None:
    """What a killed replacement left beside `out_dir` (called under the run folder's lock, so
    no live run owns it): an unfinished new run (`.NAME.new-PID`) is deleted; an old run moved
    aside (`.NAME.replaced-PID`) goes back where the new one did not arrive whole (no
    metrics.json in the folder), and is deleted where it did. Each is said."""
    for staging in out_dir.parent.glob(f".{out_dir.name}.new-*"):
        shutil.rmtree(staging, ignore_errors=True)
        print(
            f"note: removed {staging}, a replacement of {out_dir} that was interrupted",
            file=sys.stderr,
        )
    for aside in out_dir.parent.glob(f".{out_dir.name}.replaced-*"):
        if not (out_dir / "metrics.json").is_file():
            for p in list(out_dir.iterdir()) if out_dir.is_dir() else []:
                if _written_by_us(p):
                    shutil.rmtree(p) if p.is_dir() else p.unlink()
            _move_outputs(aside, out_dir, metrics_first=False)
            print(
                f"note: {out_dir}: put back the finished run an interrupted replacement had "
                "moved aside",
                file=sys.stderr,
            )
        shutil.rmtree(aside, ignore_errors=True)


def remove_if_empty(out_dir: Path) -> None:
    """Remove a run folder that holds nothing (a refused run; its lock file aside)."""
    try:
        entries = [p for p in out_dir.iterdir() if p.name != ".lock"]
        if not entries:
            (out_dir / ".lock").unlink(missing_ok=True)
            out_dir.rmdir()
    except OSError:
        pass


def check_writable(out_dir: Path) -> None:
    """Stop in one line when the run folder cannot be written."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".write_test_{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        print(
            f"error: the run folder {out_dir} cannot be written ({exc.strerror or exc}); choose "
            "another hydra.run.dir or fix its permissions",
            file=sys.stderr,
        )
        raise SystemExit(2) from None
