"""Shared by the entry points: run-directory guard, config plumbing, output writers."""

from __future__ import annotations

import json
import logging
import os
import random
import sys
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sagonline.consensus import VoteConfig
from sagonline.feedback import FeedbackConfig
from sagonline.pipeline import PipelineSettings, SceneReport
from sagonline.refine import RefineConfig
from sagonline.utils import atomic_write_json, atomic_write_text, describe_device


@dataclass
class RefineStage(RefineConfig):
    """Stage II as the harness runs it: the student's settings and whether it runs."""

    enabled: bool = True


def register_schemas() -> None:
    """The dataclasses are Hydra's schemas: conf/consensus/*.yaml, conf/refine/student.yaml
    and conf/scenes.yaml's `fit` only select and override them, so each default lives once (in
    the dataclass) and a wrong type or an unknown key fails at composition, naming the key."""
    from hydra.core.config_store import ConfigStore

    from sagonline.fitting import FitConfig

    store = ConfigStore.instance()
    store.store(group="consensus", name="schema", node=VoteConfig)
    store.store(group="fit", name="schema", node=FitConfig)
    store.store(group="refine", name="schema", node=RefineStage)
    store.store(group="feedback", name="schema", node=FeedbackConfig)


register_schemas()


class RunExists(SystemExit):
    """A finished run is in the way: refused, nothing of it was touched."""


# Settings that change how a run is shown or stored, never its numbers: a finished run with
# other values of these is still the same run.
PRESENTATION_KEYS = ("overwrite", "progress", "record", "cache", "cache_dir", "threads")


def comparable_config(config: dict) -> dict:
    """A resolved config as flat `a.b.c: value` pairs, without PRESENTATION_KEYS."""
    return flatten({k: v for k, v in config.items() if k not in PRESENTATION_KEYS and k != "hydra"})


def config_fingerprint(cfg: DictConfig) -> tuple[str, dict]:
    """Digest of the resolved config without PRESENTATION_KEYS, and the flat dict it hashes."""
    from sagonline.provenance import digest_json

    flat = comparable_config(OmegaConf.to_container(cfg, resolve=True))
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


REQUIRED_METRICS = ("dataset", "scenes", "miou")


def read_run_metrics(path: Path) -> dict | None:
    """A run's metrics.json for reports and tables, or None (with a warning naming the file and
    the problem) when it is unreadable, truncated, or lacks what a row needs: one bad run never
    aborts a report, nor becomes a silent row of blanks."""
    try:
        metrics = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        problem = f"unreadable ({type(exc).__name__}: {exc})"
    else:
        missing = (
            [k for k in REQUIRED_METRICS if k not in metrics] if isinstance(metrics, dict) else []
        )
        if isinstance(metrics, dict) and not missing:
            return metrics
        problem = f"lacks {missing}" if missing else "is not a JSON object"
    print(f"warning: skipped {path}: {problem}", file=sys.stderr)
    return None


def finished_run(out_dir: Path) -> dict | None:
    """The metrics of a finished run in `out_dir` (one that scored at least one scene), else
    None: no run, an interrupted one, or one whose every scene failed (rerun freely)."""
    path = out_dir / "metrics.json"
    if not path.is_file():
        return None
    try:
        metrics = json.loads(path.read_text())
    except (OSError, ValueError):
        raise RunExists(
            f"error: {path} is unreadable; move it away or pass overwrite=true"
        ) from None
    return None if metrics.get("status") == "failed" else metrics


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


def write_hydra_files(out_dir: Path, cfg: DictConfig) -> list[str]:
    """`.hydra/{config,hydra,overrides}.yaml` of this run, written by us once the run is
    allowed to proceed (Hydra's own copy is off: `hydra.output_subdir: null`), so a refused
    rerun never rewrites a finished run's record. Returns the command-line overrides."""
    from hydra.core.hydra_config import HydraConfig

    try:
        hydra_cfg = HydraConfig.get()
    except ValueError:  # composed directly (tests): no Hydra job
        return []
    overrides = list(hydra_cfg.overrides.task)
    atomic_write_text(out_dir / ".hydra" / "config.yaml", OmegaConf.to_yaml(cfg))
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


FILE_ONLY = {"file_only": True}  # `extra=` of records that are for eval.log, not the console


def _not_file_only(record: logging.LogRecord) -> bool:
    return not getattr(record, "file_only", False)


@contextmanager
def run_log(out_dir: Path):
    """`<run dir>/eval.log` receives every log record and warning of the run; warnings also
    reach the console (records logged with `extra=FILE_ONLY` stay out of it)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    consoles = list(root.handlers)
    for h in consoles:
        h.addFilter(_not_file_only)
    file_handler = logging.FileHandler(out_dir / "eval.log")
    file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handlers = [file_handler]
    if not root.handlers:
        console = logging.StreamHandler(sys.stderr)
        console.setLevel(logging.WARNING)
        console.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        handlers.append(console)
    old_level = root.level
    root.setLevel(logging.INFO)
    for h in handlers:
        root.addHandler(h)
    logging.captureWarnings(True)
    try:
        yield
    finally:
        logging.captureWarnings(False)
        for h in handlers:
            root.removeHandler(h)
            h.close()
        for h in consoles:
            h.removeFilter(_not_file_only)
        root.setLevel(old_level)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (legacy global RNG some plug-ins still use)
    torch.manual_seed(seed)


def quiet(cfg: DictConfig) -> bool:
    return not cfg.get("progress", True) or os.environ.get("CI", "").lower() in ("1", "true")


def settings_from(cfg: DictConfig) -> PipelineSettings:
    return PipelineSettings(
        backend=cfg.renderer.backend,
        device=cfg.device,
        label_min_weight=cfg.label_render.min_weight,
        resize=cfg.metrics.resize,
        progress=not quiet(cfg),
        feedback=OmegaConf.to_object(cfg.feedback),
    )


def refine_config_from(cfg: DictConfig) -> RefineConfig:
    """The student's settings, checked (bounds, and a `refine.pretrained` file that opens with
    weights_only) before any work: a problem stops with the key's name."""
    d = OmegaConf.to_container(cfg.refine, resolve=True)
    d.pop("enabled", None)
    try:
        refine = RefineConfig(**d)
        if refine.pretrained:
            from sagonline.refine.network import ResNetEncoder, load_imagenet_weights

            load_imagenet_weights(ResNetEncoder(refine.encoder), refine.pretrained)
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    return refine


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


def vote_config_from(cfg: DictConfig) -> VoteConfig:
    """The vote settings, type-checked against `VoteConfig`: a wrong type, an unknown key or
    an invalid value stops with the key's name."""
    try:
        given = OmegaConf.to_container(cfg.consensus, resolve=True)
        merged = OmegaConf.merge(OmegaConf.structured(VoteConfig), given)
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or "?"
        msg = str(exc).splitlines()[0]
        print(f"error: consensus.{key}: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def set_threads(cfg: DictConfig) -> int:
    """Threads for this job's torch ops and compiled kernels: `threads`, else the cores a
    submitit job was given (hydra.launcher.cpus_per_task), else the machine's cores divided
    among the jobs joblib runs at once (hydra.launcher.n_jobs), so parallel jobs do not
    oversubscribe the cores."""
    threads = cfg.get("threads")
    if not threads:
        from hydra.core.hydra_config import HydraConfig

        try:
            launcher = HydraConfig.get().launcher
        except ValueError:  # composed directly (tests): no Hydra job
            return torch.get_num_threads()
        jobs = int(launcher.get("n_jobs") or 1)  # joblib: jobs at once on this machine
        threads = launcher.get("cpus_per_task")  # submitit: the job's own cores
        if not threads and jobs <= 1:
            return torch.get_num_threads()
        threads = threads or max(1, (os.cpu_count() or 1) // jobs)
    torch.set_num_threads(int(threads))
    return int(threads)


def check_device(device: str) -> None:
    """Stop before any work when the requested device does not exist here."""
    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        print(f"error: device={device}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(
            f"error: device={device}: CUDA is not available here (torch {torch.__version__}); "
            "use device=cpu",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        print(
            f"error: device={device}: only {torch.cuda.device_count()} CUDA device(s) here",
            file=sys.stderr,
        )
        raise SystemExit(2)


def build_plugin(node: DictConfig, what: str):
    """Instantiate a plug-in; a configuration problem stops with its own message, not a trace."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate(plugin_kwargs(node))
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        print(f"error: {what} {node.get('name', '')}: {cause}", file=sys.stderr)
        raise SystemExit(2) from None


def plugin_kwargs(node: DictConfig) -> dict:
    """A plug-in's config without the keys that are ours, not its constructor's."""
    d = OmegaConf.to_container(node, resolve=True)
    d.pop("name", None)
    return d


def write_outputs(
    out_dir: Path,
    cfg: DictConfig,
    reports: list[SceneReport],
    summary: dict,
    extra: dict | None = None,
) -> dict:
    """metrics.json (+ per_view.csv) atomically into the run directory."""
    from sagonline.metrics import RESIZE_RULES

    metrics = {
        "dataset": cfg.dataset.name,
        "segmenter": cfg.segmenter.get("name", "segmenter"),
        "consensus": OmegaConf.to_container(cfg.consensus, resolve=True),
        "renderer": cfg.renderer.backend,
        **summary,
        "resize_rule": RESIZE_RULES[cfg.metrics.resize],
        "device": describe_device(cfg.device),
        "scenes": [{k: v for k, v in asdict(r).items() if k != "views"} for r in reports],
        "config": OmegaConf.to_container(cfg, resolve=True),
        **(extra or {}),
    }
    rows = [v for r in reports for v in r.views]
    columns = ["scene", "view", "mode", "iou", "acc", "voted"]
    columns += [
        k
        for k in ("photographed", "photo_angle_deg", "photo_distance")
        if any(k in r for r in rows)
    ]
    atomic_write_text(
        out_dir / "per_view.csv", pd.DataFrame(rows, columns=columns).to_csv(index=False)
    )
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def fmt(x, pct: bool = True) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.2f}" if pct else f"{x:.1f}"


def print_summary(out_dir: Path, metrics: dict, reports: list[SceneReport]) -> None:
    """One screen: per-scene rows, overall numbers, where the outputs are."""
    lines = [
        f"dataset {metrics['dataset']}  segmenter {metrics['segmenter']}  "
        f"consensus {metrics['consensus']['method']}  renderer {metrics['renderer']}",
        "",
    ]
    lines.append(
        f"{'scene':<22}{'status':<9}{'mIoU':>8}{'mAcc':>8}{'seg mIoU':>10}"
        f"{'3D acc':>8}{'3D cov':>8}{'vote ms/mask':>14}{'refined':>9}"
    )
    for r in reports:
        l3 = r.labels3d or {}
        lines.append(
            f"{r.scene:<22}{r.status:<9}{fmt(r.miou):>8}{fmt(r.macc):>8}"
            f"{fmt(r.segmenter_miou):>10}{fmt(l3.get('accuracy')):>8}"
            f"{fmt(l3.get('coverage')):>8}"
            f"{fmt(r.timings.get('vote_ms_per_mask'), False):>14}{fmt(r.refined_miou):>9}"
        )
        if r.error:
            lines.append(f"    {r.error}")
    lines += [
        "",
        f"overall mIoU {fmt(metrics['miou'])}  mAcc {fmt(metrics['macc'])}  "
        f"segmenter mIoU {fmt(metrics['segmenter_miou'])}"
        + (f"  refined mIoU {fmt(metrics['refined_miou'])}" if metrics.get("refined_miou") else "")
        + ("   (PARTIAL: some scenes failed)" if metrics.get("partial") else ""),
        f"resize rule: {metrics['resize_rule']}",
        f"outputs: {out_dir}/metrics.json, per_view.csv"
        + (
            ", recording.rrd (open with: rerun recording.rrd)"
            if (out_dir / "recording.rrd").exists()
            else ""
        ),
    ]
    text = "\n".join(lines)
    print(text)
    logging.getLogger("sagonline.eval").info("summary\n%s", text, extra=FILE_ONLY)
