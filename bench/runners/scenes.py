"""Fit the Gaussian scene a dataset needs: `make scenes DATASET=<name> [SCENE=<scene>]`.

For each scene: read its images and cameras, downsample to `fit.max_side`, initialise from
COLMAP points where the capture has them, else from SIFT matches triangulated with the training
cameras fixed (pycolmap), else random points in the training frusta,
fit (sagonline.fitting), and write point_cloud.ply + cameras.json + fit_config.json +
fit_metrics.json where the dataset adapter looks (`<scene>/gaussians/`, or
`scenes/<dataset>/<scene>/gaussians/` when the data folder is read-only), with side-by-side
renders of the held-out views to look at. Interrupted fits resume from fit_checkpoint.store.
"""

from __future__ import annotations

import os

# A fit pins torch's CPU kernels to AVX2 (read once, when torch loads): AVX-512 kernels round
# differently, and the same fit then gives another scene. It also pins MKL, torch's BLAS, to
# its COMPATIBLE branch, which gives the same results on every x86 CPU: unpinned on an Intel
# CPU with AVX-512, MKL took its own faster branch there (another draw than on an AMD CPU, both
# AVX2-pinned) and one of four identical 150-iteration fits differed from the others (its
# branches' results depend on the data's memory alignment); pinned, 2 of 2 came out the same, as
# fast (docs/fitting.md). fit_metrics.json records both pins.
os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")
os.environ.setdefault("MKL_CBWR", "COMPATIBLE")

import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from bench.runners.config import (
    ScenesConfig,
    register_schemas_or_exit,
    to_config,
)
from bench.runners.job import build_dataset, quiet
from bench.runners.overrides import check_override_keys, options_first
from bench.runners.scenes_finish import (
    finish_scene,
    finished_base,
    partner_means,
    recipe_json,
)
from sagonline.core.files import atomic_write_image
from sagonline.core.machine import cpu_capability
from sagonline.core.outputs import RunLock
from sagonline.datasets.base import DatasetError
from sagonline.datasets.fits import copy_fit, fit_folder, fit_variant, foreign_scene, output_dir
from sagonline.fitting import FitConfig, SceneFitter, psnr_from_mse, write_fitted_scene
from sagonline.fitting.capture import (
    fit_near_depths,
    initial_points,
    load_images,
    near_depth,
    resolve_background,
)
from sagonline.fitting.config import as_recorded
from sagonline.fitting.finish import adopt_finished
from sagonline.scene.io import read_scene
from sagonline.scene.io.cameras import load_llff_bounds
from sagonline.scene.io.images import resize_nearest


def variant_of(cfg: ScenesConfig) -> str:
    """The fit's folder suffix: `seed<k>` for a seed other than 0 (each draw of the recipe in a
    folder of its own; evaluate one with dataset.adapter.fit=seed<k>), after `variant` where
    one is named (`<variant>-seed<k>`: the draws of a variant recipe side by side too)."""
    return fit_variant(cfg.variant, cfg.seed)


def object_psnr(adapter, scene: str, fitter: SceneFitter, renders: dict) -> float | None:
    """Mean held-out PSNR over the pixels inside the dataset's own object masks (None when the
    held-out views have none): how well the fit shows what gets segmented, apart from the
    background that few training views see. renders: view index -> (H, W, 3) render."""
    try:
        _, mask_paths = adapter.load_views(scene)
    except (AttributeError, DatasetError):
        return None
    values = []
    for i, rgb in renders.items():
        cam = fitter.cams[i]
        if cam.name not in mask_paths:
            continue
        labels = adapter.read_label_map(mask_paths[cam.name])
        inside = resize_nearest((labels > 0).astype(np.uint8), (cam.height, cam.width)) > 0
        if not inside.any():
            continue
        err = ((rgb.to(fitter.images[i].device) - fitter.images[i]) ** 2).mean(-1)
        err = err[torch.from_numpy(inside).to(err.device)]
        values.append(psnr_from_mse(float(err.mean())))
    return float(np.mean(values)) if values else None


def may_fit(cfg: ScenesConfig, out: Path, scene: str) -> bool:
    """False (and says why) when `out` holds a finished fit or a scene that is not ours and
    overwrite is off."""
    if cfg.overwrite:
        return True
    foreign = foreign_scene(out)
    if foreign is None and (out / "point_cloud.ply").is_file():
        print(f"{scene}: already fitted ({out}); pass overwrite=true to fit again")
        return False
    if foreign is not None:
        print(
            f"{scene}: {foreign} is a trained scene that `make scenes` did not write (its "
            "digest is not the one fit_metrics.json records); it is left as it is. Pass "
            "overwrite=true to fit anyway (it is then kept as a .bak file).",
            file=sys.stderr,
        )
        return False
    return True


def other_fits(out: Path, seed: int) -> list[Path]:
    """The capture's fits beside `out` whose start points it may share: the seed's fit of the
    default recipe first, then the others (another recipe, or the same one stopped at a budget);
    `initial_points` takes the first whose cached points were triangulated from the same
    views, seed and detector settings."""
    default = out.with_name(fit_folder(fit_variant(None, seed)))
    siblings = sorted(p for p in out.parent.glob(fit_folder() + "-*") if p.is_dir())
    return [p for p in dict.fromkeys([default, *siblings]) if p != out]


def build_fitter(cfg: ScenesConfig, scene_dir: Path, cams, images, out: Path):
    """The fitter of one capture: images at the fitting size, start points, clearances."""
    fit_cfg = dataclasses.replace(cfg.fit)  # this scene's copy (its clearance is set below)
    train_cams, train_imgs = load_images(cams, images, fit_cfg.max_side)
    resolve_background(fit_cfg, train_imgs)  # fit_config.json records what it sets
    bounds = near_far = None
    if (scene_dir / "poses_bounds.npy").is_file():
        b = load_llff_bounds(scene_dir)
        bounds = (float(b[:, 0].min()), float(b[:, 1].max()))
        near_far = (bounds[0] * 0.9, bounds[1] * 1.1)  # random start points: a little beyond
    points, init = initial_points(
        fit_cfg, scene_dir, train_cams, images, out, other_fits(out, cfg.seed)
    )
    if fit_cfg.camera_clearance is None:  # auto: half the nearest depth the capture records
        fit_cfg.camera_clearance = 0.5 * near_depth(train_cams, points, bounds)
    fitter = SceneFitter(
        fit_cfg,
        train_cams,
        train_imgs,
        points,
        near_far,
        other_cameras=[c for c in cams if c.name not in images],
        view_near=fit_near_depths(scene_dir, cams, points, images, fit_cfg.view_near_quantile)
        if fit_cfg.view_clearance or fit_cfg.pose_view_clearance
        else None,
    )
    return fitter, init


def fit_scene(cfg: ScenesConfig, adapter, scene: str) -> dict:
    """Fit one scene of `adapter` where it looks for it; returns fit_metrics.json's content."""
    scene_dir, cams, images = adapter.capture(scene)
    if len(images) < 2:
        raise DatasetError(
            f"{adapter.name}/{scene}: {len(images)} images with cameras; fitting needs at least two"
        )
    out = output_dir(scene_dir, adapter.name, variant_of(cfg))
    with RunLock(out):  # a second fit into this folder is refused, not interleaved
        if not may_fit(cfg, out, scene):
            return {"scene": scene, "skipped": True}
        return fit_locked(cfg, adapter, scene, scene_dir, cams, images, out)


def fit_pins() -> dict[str, str | None]:
    """What a fit's rounding depends on besides its recipe (pinned above unless set otherwise):
    torch's CPU vector width and MKL's branch; fit_metrics.json records them."""
    return {"cpu_capability": cpu_capability(), "mkl_cbwr": os.environ.get("MKL_CBWR")}


def same_fit_as(cfg: ScenesConfig, scene_dir, cams, images, fitter, out: Path):
    """The seed's finished fit in its own folder (gaussians/ or gaussians-seed<k>/) when the
    fit of `fitter` into the variant folder `out` would repeat it: the recipes differ in
    `fit.view_near_quantile` and `fit.backdrop` at most, and both fitters render on the same
    background and start from the same Gaussians with the same near depth in every view the
    clearances use (on this capture those settings then change nothing), under the same
    `fit_pins` (another vector width or MKL branch rounds otherwise: another draw of the
    recipe). None otherwise, and always without a variant."""
    base = out.with_name(fit_folder(fit_variant(None, cfg.seed)))
    if cfg.variant is None or base == out or not (base / "fit_config.json").is_file():
        return None
    if not (base / "point_cloud.ply").is_file() or foreign_scene(base) is not None:
        return None
    recorded_metrics = json.loads((base / "fit_metrics.json").read_text())
    if any(recorded_metrics.get(k) != v for k, v in fit_pins().items()):
        return None  # another width or branch, or a fit before a pin: another draw
    mine, today = recipe_json(fitter.cfg), recipe_json(FitConfig())
    # a fit that predates a setting ran without it: it stands for that setting's default (as
    # wherever a finished fit is reused), but for the settings whose rule before them differed
    recorded = as_recorded(json.loads((base / "fit_config.json").read_text()), today)
    free = ("view_near_quantile", "backdrop")  # the background they resolve to is compared
    theirs = {k: recorded.pop(k) for k in free}
    for k in free:
        mine.pop(k)
    if recorded != mine:
        return None
    base_fit = dataclasses.replace(cfg.fit, **theirs)
    other, _ = build_fitter(dataclasses.replace(cfg, fit=base_fit), scene_dir, cams, images, base)

    def near(f):
        return [(c.name, d) for c, d in [*f.strategy.views, *f.strategy.pose_views]]

    same = near(other) == near(fitter) and other.params.keys() == fitter.params.keys()
    same = same and all(torch.equal(other.params[k], fitter.params[k]) for k in fitter.params)
    return base if same and other.train_idx == fitter.train_idx else None


def fit_locked(cfg: ScenesConfig, adapter, scene: str, scene_dir, cams, images, out: Path) -> dict:
    """`fit_scene` once `out` is locked."""
    if cfg.fit.co_prune_seed is not None and cfg.finish_from is None:
        raise DatasetError("fit.co_prune_seed acts on finished fits: give finish_from=V too")
    fitter, init = build_fitter(cfg, scene_dir, cams, images, out)
    base = same_fit_as(cfg, scene_dir, cams, images, fitter, out)
    if base is not None:
        print(
            f"{scene}: this recipe's fit is the one in {base} (the same start and near depths; "
            f"fit.view_near_quantile or fit.backdrop change nothing here): copied to {out}"
        )
        return copy_fit(base, out, dataclasses.asdict(fitter.cfg))
    ckpt = out / "fit_checkpoint.store"
    if fitter.resume(ckpt):
        print(f"{scene}: resuming at iteration {fitter.step}")
    elif cfg.finish_from is not None:
        base = finished_base(cfg, fitter, out)
        adopt_finished(fitter, read_scene(base / "point_cloud.ply"))
        fitter.partner_means = partner_means(cfg, fitter, base)
        print(f"{scene}: starting after the last iteration, from the fit in {base}")
    metrics = fitter.fit(progress=not quiet(cfg), checkpoint=ckpt)
    first = fitter.cams[0]
    metrics.update(
        {
            "scene": scene,
            "dataset": adapter.name,
            "images": len(fitter.images),
            "resolution": [first.width, first.height],
            "init": init,
            "threads": torch.get_num_threads(),  # the fit is the same on any count (recorded)
            **fit_pins(),
        }
    )
    with torch.no_grad():
        on_device = fitter.export().to(fitter.cfg.device)
        renders = {i: fitter.render(on_device, i).rgb.clamp(0, 1).cpu() for i in fitter.held_idx}
    metrics["psnr_heldout_object"] = object_psnr(adapter, scene, fitter, renders)
    foreign = foreign_scene(out)  # asked now: whatever happened while this fit ran
    if foreign is not None:  # overwrite=true: keep the scene that is not ours beside ours
        backup = foreign.with_name(f"{foreign.name}.bak-{time.strftime('%Y%m%d-%H%M%S')}")
        foreign.rename(backup)
        print(f"{scene}: the scene that was there is now {backup}")
    write_fitted_scene(out, fitter, cams, metrics)
    for i, render in renders.items():
        pair = np.concatenate([render.numpy(), fitter.images[i].cpu().numpy()], axis=1)
        atomic_write_image(
            out / f"heldout_{fitter.cams[i].name}.png", (pair * 255 + 0.5).astype(np.uint8)
        )
    ckpt.unlink(missing_ok=True)
    print_fit(scene, fitter.cfg, metrics, out)
    return metrics


def print_fit(scene: str, fit_cfg: FitConfig, metrics: dict, out: Path) -> None:
    if metrics["stopped"] == "time_budget":
        print(
            f"WARNING: {scene}: the fit stopped at its time budget (fit.time_budget_s="
            f"{fit_cfg.time_budget_s}) after {metrics['iterations']} of "
            f"{metrics['iterations_planned']} iterations; the scene depends on how busy the "
            "machine was. Every run on it will say so.",
            file=sys.stderr,
        )
    on_object = metrics["psnr_heldout_object"]
    print(
        f"{scene}: PSNR train {metrics['psnr_train']:.2f} dB, held-out "
        f"{metrics['psnr_heldout']:.2f} dB"
        + (f" ({on_object:.2f} dB inside the object masks)" if on_object else "")
        + f", {metrics['gaussians']} Gaussians, "
        f"{metrics['fit_seconds']:.0f} s -> {out}"
    )


@hydra.main(version_base="1.3", config_path="../../conf", config_name="scenes")
def main(dict_cfg: DictConfig) -> None:
    try:
        fit_all(dict_cfg)
    except SystemExit:
        forget_refused_run(Path(HydraConfig.get().runtime.output_dir))
        raise
    except OSError as exc:  # a full disk, a file size limit, a folder gone read-only
        from bench.runners.runlog import disk_words

        print(f"error: {disk_words(exc)}", file=sys.stderr)
        raise SystemExit(2) from None


def forget_refused_run(run: Path) -> None:
    """A command refused before any fit leaves no folder behind (only Hydra's record and the
    log were in it)."""

    if run.is_dir() and {p.name for p in run.iterdir()} <= {".hydra", "scenes.log"}:
        shutil.rmtree(run, ignore_errors=True)


def fit_all(dict_cfg: DictConfig) -> None:
    """Fit (or finish) every scene the config names; a scene that cannot be fitted is named
    and the others go on; exit 2 if any failed."""
    cfg: ScenesConfig = to_config(dict_cfg, ScenesConfig)
    adapter = build_dataset(cfg.dataset)
    try:
        names = [cfg.scene] if cfg.scene else adapter.scene_names()
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if not hasattr(adapter, "capture"):
        print(
            f"error: dataset {cfg.dataset['name']} has no captured images to fit "
            "(the synthetic scenes are generated, not fitted)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    failed = []
    for scene in names:
        try:
            (finish_scene if cfg.finish else fit_scene)(cfg, adapter, scene)
        except DatasetError as exc:
            print(f"error: {scene}: {exc}", file=sys.stderr)
            failed.append(scene)
    if failed:
        raise SystemExit(2)


if __name__ == "__main__":
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    sys.argv[1:] = options_first(sys.argv[1:])
    check_override_keys(ScenesConfig, sys.argv[1:], "bench.runners.scenes")
    register_schemas_or_exit()
    main()
