"""What a run writes and prints: metrics.json, per_view.csv and the console summary."""

from __future__ import annotations

import logging
import math
from dataclasses import asdict
from pathlib import Path

import pandas as pd

from sagonline.core.files import atomic_write_json, atomic_write_text
from sagonline.core.machine import describe_device
from sagonline.pipeline import SceneReport
from sagonline.pipeline.evaluate import FILE_ONLY
from sagonline.record.recording import viewer_command
from sagonline.score.run_metrics import METRICS_VERSION, RunMetrics


def resize_rule(cfg) -> str:
    """How the scored label maps meet the ground truth's size, in words."""
    from sagonline.score.metrics import RESIZE_RULES

    rule = RESIZE_RULES[cfg.metrics.resize]
    if cfg.label_render.size == "truth":
        return (
            f"label renders at the ground truth's resolution (label_render.size=truth); else {rule}"
        )
    return rule


def write_outputs(
    out_dir: Path,
    cfg,
    reports: list[SceneReport],
    summary: dict,
    extra: dict | None = None,
) -> dict:
    """metrics.json, per_view.csv (and gaussians_outside.csv where the diagnosis found labelled
    Gaussians outside the object's silhouette) atomically into the run directory."""
    from sagonline.score.predictions import folder_sha256

    folders = ("predictions", "predictions_refined", "ground_truth")
    digests = {f: folder_sha256(out_dir / f) for f in folders if (out_dir / f).is_dir()}
    record = {
        "dataset": cfg.dataset["name"],
        "segmenter": cfg.segmenter.get("name", "segmenter"),
        "consensus": asdict(cfg.consensus),
        "renderer": cfg.renderer.backend,
        **summary,
        "resize_rule": resize_rule(cfg),
        "device": describe_device(cfg.device),
        "sha256": digests,  # of the label-map PNGs: re-score with sagonline score
        "scenes": [
            {k: v for k, v in asdict(r).items() if k not in ("views", "outside")} for r in reports
        ],
        "config": asdict(cfg),
        **(extra or {}),
        "version": METRICS_VERSION,
    }
    metrics = RunMetrics.from_json(record).to_json()  # the schema's fields, checked
    rows = [{**v, "protocol": r.protocol} for r in reports for v in r.views]
    columns = ["protocol", "scene", "view", "mode", "iou", "acc", "voted"]
    from sagonline.score.alignment import SHIFT_KEYS
    from sagonline.score.diagnosis import EXTRA, MISSED

    diagnosis = ("object_px", "hidden_px", *SHIFT_KEYS, "missed_px", *MISSED, "extra_px", *EXTRA)
    columns += [
        k
        for k in ("photographed", "photo_angle_deg", "photo_distance", *diagnosis)
        if any(k in r for r in rows)
    ]
    atomic_write_text(
        out_dir / "per_view.csv", pd.DataFrame(rows, columns=columns).to_csv(index=False)
    )
    outside = [{"scene": r.scene, **row} for r in reports for row in r.outside]
    if outside:  # the labelled Gaussians shown outside the silhouette (score.diagnosis)
        atomic_write_text(
            out_dir / "gaussians_outside.csv", pd.DataFrame(outside).to_csv(index=False)
        )
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def folder_bytes(path: Path) -> int:
    """Bytes of the files below `path` (0 when it does not exist)."""
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.exists() else 0


def disk_line(out_dir: Path, cache: Path | None, home: Path | None = None) -> str:
    """What the run takes on disk: its folder, and the stage cache it wrote into (`home`: the
    run folder, where `out_dir` is a replacement staged beside it and the cache is home's)."""
    home = home or out_dir
    cached = folder_bytes(cache) if cache is not None and cache.exists() else None
    inside = cached is not None and cache.resolve().is_relative_to(home.resolve())
    run = folder_bytes(out_dir)
    if inside and home != out_dir:  # a staged replacement: its cache is the run folder's
        run += cached
    line = f"disk: run folder {run / 1e6:.2f} MB"
    if inside:
        line += f" (its cache {cached / 1e6:.1f} MB)"
    elif cached is not None:
        line += (
            f", shared stage cache {cache} {cached / 1e6:.1f} MB (keyed by content: safe to "
            "delete; make clean-cache empties .cache/stages)"
        )
    return line


def fmt(x, pct: bool = True) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.2f}" if pct else f"{x:.1f}"


def timed(timings: dict, cached: dict, key: str) -> str:
    """A time this run took (`timings[key]`, ms); else the one a run that filled the stage cache
    took for the stage this run was served (`cached[key]`), marked `*` (CACHED_NOTE); else `-`."""
    if timings.get(key) is not None:
        return fmt(timings[key], False)
    return f"{fmt(cached[key], False)}*" if cached.get(key) is not None else "-"


CACHED_NOTE = "* a vote served from the stage cache: the time of the run that made it"


def diagnosis_lines(d: dict) -> list[str]:
    """A scene's diagnosis (`score.diagnosis` shares, `report.extra["diagnosis"]`) as summary
    lines: where the missed pixels were lost, what the fit hides, the views rendered displaced."""
    lines: list[str] = []
    if d.get("missed_px"):
        lines.append(
            f"    missed pixels {d['missed_px']}: fit {fmt(d['share_fit'])}%, vote "
            f"{fmt(d['share_vote'])}%, segmenter {fmt(d['share_segmenter'])}% "
            "(per view: per_view.csv; the causes: sagonline/score/diagnosis.py)"
        )
    if d.get("hidden"):
        lines.append(
            f"    the fit hides {fmt(d['hidden'])}% of the object's pixels behind nearer "
            f"surfaces ({d.get('hidden_views', 0)} views more than a tenth: per_view.csv "
            "hidden_px / object_px)"
        )
    if d.get("displaced"):
        shown = ", ".join(
            f"{v['view']} {math.hypot(v['shift_dx'], v['shift_dy']):.0f} px "
            f"({v['silhouette_iou']:.2f} -> {v['shifted_iou']:.2f})"
            for v in d["displaced"][:5]
        )
        more = f" and {len(d['displaced']) - 5} more" if len(d["displaced"]) > 5 else ""
        lines.append(
            f"    the object is rendered displaced from its mask in {len(d['displaced'])} "
            f"view(s) (a camera's pose?): {shown}{more} (view, shift, silhouette IoU unshifted "
            "-> shifted; per_view.csv shift_dx, shift_dy)"
        )
    return lines


def print_summary(
    out_dir: Path,
    metrics: dict,
    reports: list[SceneReport],
    cache: Path | None = None,
    shown_as: Path | None = None,
) -> None:
    """One screen: per-scene rows, overall numbers, where the outputs are (`shown_as`: the
    folder they will be in, where `out_dir` is a replacement staged beside it)."""
    plan, shown = metrics.get("backends") or {}, shown_as or out_dir
    verdict = "   (PARTIAL: some scenes failed)" if metrics.get("partial") else ""
    if not metrics.get("scenes_scored"):
        verdict = "   (FAILED: no scene was scored)"
    lines = [
        f"dataset {metrics['dataset']}  segmenter {metrics['segmenter']}  "
        f"consensus {metrics['consensus']['method']}  renderer {metrics['renderer']}",
        f"protocol {metrics.get('protocol_id') or '-'}",
        f"ran on {plan.get('device', '-')}: images {plan.get('images', '-')}, vote "
        f"{plan.get('vote', '-')}, label renders {plan.get('labels', '-')}"
        + (f" ({metrics['device']['gpu']})" if metrics["device"].get("gpu") else ""),
        "",
    ]
    lines.append(
        f"{'scene':<22}{'status':<9}{'mIoU':>8}{'mAcc':>8}{'seg mIoU':>10}"
        f"{'3D acc':>8}{'3D cov':>8}{'vote ms/mask':>14}{'refined':>9}"
    )
    votes = [timed(r.timings, r.cached_timings, "vote_ms_per_mask") for r in reports]
    for r, vote in zip(reports, votes, strict=True):
        l3 = r.labels3d or {}
        lines.append(
            f"{r.scene:<22}{r.status:<9}{fmt(r.miou):>8}{fmt(r.macc):>8}"
            f"{fmt(r.segmenter_miou):>10}{fmt(l3.get('accuracy')):>8}"
            f"{fmt(l3.get('coverage')):>8}"
            f"{vote:>14}"
            f"{fmt(r.refined_miou):>9}"
        )
        if r.error:
            lines.append(f"    {r.error}")
        lines += diagnosis_lines(r.extra.get("diagnosis") or {})
        groups = r.extra.get("by_view_group") or {}
        for key, value in groups.items():  # e.g. photographed / mask-only views of a capture
            if key.endswith("_miou") and value is not None:
                views = groups.get(key.removesuffix("_miou") + "_views")
                lines.append(f"    {key.removesuffix('_miou')}: mIoU {fmt(value)} ({views} views)")
    if any(vote.endswith("*") for vote in votes):
        lines.append(CACHED_NOTE)
    lines += [
        "",
        f"overall mIoU {fmt(metrics['miou'])}  mAcc {fmt(metrics['macc'])}  "
        f"segmenter mIoU {fmt(metrics['segmenter_miou'])}"
        + (f"  refined mIoU {fmt(metrics['refined_miou'])}" if metrics.get("refined_miou") else "")
        + verdict,
        f"resize rule: {metrics['resize_rule']}",
        f"outputs: {shown}/metrics.json, per_view.csv"
        + (", predictions/ (sagonline score)" if (out_dir / "predictions").is_dir() else "")
        + (
            f", recording.rrd (open with: {viewer_command(shown / 'recording.rrd')})"
            if (out_dir / "recording.rrd").exists()
            else ""
        ),
        disk_line(out_dir, cache, shown_as),
    ]
    text = "\n".join(lines)
    print(text)
    logging.getLogger("sagonline.eval").info("summary\n%s", text, extra=FILE_ONLY)
