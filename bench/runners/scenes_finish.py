"""The steps of `make scenes` after a fit's last iteration, on fits already made: a finished fit
taken up as this recipe's state after its last iteration (`finish_from`, checked to be the same
recipe but for `AFTER_THE_FIT`), a second draw of it for the co-pruning (`fit.co_prune_seed`),
and `finish=true` on a fit that predates the pose-view clearance."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch

from bench.runners.config import ScenesConfig
from sagonline.core.files import atomic_write_json, to_json
from sagonline.core.provenance import digest_file
from sagonline.datasets.base import DatasetError
from sagonline.datasets.fits import fit_folder, fit_variant, foreign_scene, output_dir
from sagonline.fitting import FitConfig, SceneFitter
from sagonline.fitting.capture import initial_points, load_images, view_near_depths
from sagonline.scene.io import read_scene


def recipe_json(cfg: FitConfig) -> dict:
    """A recipe as fit_config.json records it (tuples as lists), to compare with a record."""
    return json.loads(to_json(dataclasses.asdict(cfg)))


AFTER_THE_FIT = (
    "carve_views",
    "carve_margin",
    "polish_iterations",
    "polish_opacity_entropy",
    "co_prune_seed",
    "co_prune_sigmas",
)
"""The recipe's settings that act only after the last iteration (`SceneFitter.finish`)."""


def finished_base(
    cfg: ScenesConfig, fitter: SceneFitter, out: Path, free: tuple[str, ...] = ()
) -> Path:
    """The folder of `finish_from`'s fit (of `cfg.seed`), checked: a finished fit of ours whose
    recipe is this one but for `AFTER_THE_FIT` (and `free`)."""
    name = "" if cfg.finish_from in ("", "default") else cfg.finish_from
    base = out.with_name(fit_folder(fit_variant(name, cfg.seed)))
    if base == out:
        raise DatasetError(f"finish_from={cfg.finish_from!r} is this fit's own folder ({out})")
    if not (base / "fit_config.json").is_file() or foreign_scene(base) is not None:
        raise DatasetError(f"finish_from={cfg.finish_from!r}: {base} holds no fit of ours")
    theirs = recipe_json(FitConfig()) | json.loads((base / "fit_config.json").read_text())
    mine = recipe_json(fitter.cfg)
    allowed = (*AFTER_THE_FIT, *free)
    differ = sorted(k for k in mine if k not in allowed and theirs.get(k) != mine[k])
    if differ:
        raise DatasetError(
            f"finish_from={cfg.finish_from!r}: {base} was fitted with another recipe "
            f"({', '.join(f'fit.{k}' for k in differ)} differ); only {', '.join(AFTER_THE_FIT)} "
            "may"
        )
    return base


def finish_scene(cfg: ScenesConfig, adapter, scene: str) -> dict:
    """`finish=true`: the after-the-fit steps on a finished fit that predates them (the fitted
    scene is the state they run on, so the result is what a fit with this recipe writes)."""
    from sagonline.fitting.strategy import clear_of_pose_views
    from sagonline.scene.io import write_ply

    scene_dir, cams, images = adapter.capture(scene)
    out = output_dir(scene_dir, adapter.name, fit_variant(cfg.variant, cfg.seed))
    if not (out / "point_cloud.ply").is_file() or foreign_scene(out) is not None:
        raise DatasetError(f"{out}: no fit of `make scenes` to finish (fit it first)")
    recorded = json.loads((out / "fit_config.json").read_text())
    if "pose_view_clearance" in recorded:
        print(f"{scene}: already finished (pose_view_clearance {recorded['pose_view_clearance']})")
        return {"scene": scene, "skipped": True}
    train_cams, _ = load_images(cams, images, cfg.fit.max_side)
    points, _ = initial_points(cfg.fit, scene_dir, train_cams, images, out)
    near = view_near_depths(scene_dir, cams, points)  # pose-only views: the 2nd percentile
    pose_views = [(c, near.get(c.name, 0.0)) for c in cams if c.name not in images]
    pose_views = [(c, d) for c, d in pose_views if d > 0]
    g = read_scene(out / "point_cloud.ply")
    with torch.no_grad():
        keep = clear_of_pose_views(
            g.means, torch.log(g.scales), pose_views, cfg.fit.pose_view_clearance
        )
    written = write_ply(out / "point_cloud.ply", g.subset(keep))
    recorded["pose_view_clearance"] = cfg.fit.pose_view_clearance
    metrics = json.loads((out / "fit_metrics.json").read_text())
    metrics |= {
        "pruned_pose_views": int((~keep).sum()),
        "gaussians": int(keep.sum()),
        "finished_after_fit": True,  # the PSNRs above were measured before this step
        "scene_digest": digest_file(written),
    }
    atomic_write_json(out / "fit_config.json", recorded)
    atomic_write_json(out / "fit_metrics.json", metrics)
    print(
        f"{scene}: pruned {int((~keep).sum())} of {len(g)} Gaussians reaching into "
        f"{len(pose_views)} pose-only views nearer than {cfg.fit.pose_view_clearance} x their "
        f"near depth -> {out}"
    )
    return metrics


def partner_means(cfg: ScenesConfig, fitter: SceneFitter, base: Path) -> torch.Tensor | None:
    """With `fit.co_prune_seed`: the centres (M, 3) of the base recipe's finished fit of that
    seed (`finish_from`'s variant, beside `base`), checked as `finished_base` checks `base`;
    None without it."""
    seed = cfg.fit.co_prune_seed
    if seed is None:
        return None
    if seed == cfg.seed:
        raise DatasetError(f"fit.co_prune_seed={seed} is this fit's own seed: name another draw")
    folder = finished_base(dataclasses.replace(cfg, seed=seed), fitter, base, free=("seed",))
    return read_scene(folder / "point_cloud.ply").means
