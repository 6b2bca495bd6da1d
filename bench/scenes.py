"""Fit the Gaussian scene a dataset needs: `make scenes DATASET=<name> [SCENE=<scene>]`.

For each scene: read its images and cameras, downsample to `fit.max_side`, initialise from
COLMAP points where the capture has them, else from SIFT matches triangulated with the training
cameras fixed (pycolmap), else random points in the training frusta,
fit (sagonline.fit), and write point_cloud.ply + cameras.json + fit_config.json +
fit_metrics.json where the dataset adapter looks (`<scene>/gaussians/`, or
`scenes/<dataset>/<scene>/gaussians/` when the data folder is read-only), with side-by-side
renders of the held-out views to look at. Interrupted fits resume from fit_checkpoint.pt.
"""

from __future__ import annotations

import os
import stat
import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from PIL import Image

from bench.common import register_schemas
from sagonline.cameras import load_llff_bounds, read_colmap_points
from sagonline.datasets.base import DatasetError
from sagonline.datasets.common import SCENES_ROOT
from sagonline.fit import FitConfig, SceneFitter, psnr_from_mse, split_views, write_fitted_scene
from sagonline.metrics import resize_nearest
from sagonline.triangulate import triangulate_known_poses
from sagonline.utils import atomic_write_image, atomic_write_npz


def output_dir(scene_dir: Path, dataset: str) -> Path:
    """`<scene>/gaussians/` when the data folder is writable, else the project's overlay.
    A folder whose owner-write bit is off counts as read-only even for root (who could
    write anyway), so shared, read-only data is never modified."""
    own = scene_dir / "gaussians"
    if not (scene_dir.stat().st_mode & stat.S_IWUSR):
        return SCENES_ROOT / dataset / scene_dir.name / "gaussians"
    try:
        own.mkdir(parents=True, exist_ok=True)
        probe = own / ".write_test"
        probe.write_text("")
        probe.unlink()
        return own
    except OSError:
        return SCENES_ROOT / dataset / scene_dir.name / "gaussians"


def foreign_scene(out: Path) -> Path | None:
    """A point_cloud.ply in `out` that no fit of ours wrote (neither fit_metrics.json nor an
    interrupted fit's checkpoint beside it): the user's own scene, never replaced silently."""
    scene = out / "point_cloud.ply"
    ours = (out / "fit_metrics.json").is_file() or (out / "fit_checkpoint.pt").is_file()
    return scene if scene.is_file() and not ours else None


def load_images(cams, images: dict[str, Path], max_side: int):
    """Cameras that have an image, rescaled so the longer side is at most `max_side`, and
    their images as (H, W, 3) float tensors in [0, 1]."""
    out_cams, out_imgs = [], []
    for cam in cams:
        if cam.name not in images:
            continue
        with Image.open(images[cam.name]) as im:
            im = im.convert("RGB")
            scale = min(1.0, max_side / max(im.size))
            w, h = max(1, round(im.size[0] * scale)), max(1, round(im.size[1] * scale))
            arr = np.asarray(im.resize((w, h), Image.Resampling.LANCZOS), np.float32) / 255.0
        out_cams.append(cam.scaled(w, h))
        out_imgs.append(torch.from_numpy(arr))
    return out_cams, out_imgs


def initial_points(cfg: FitConfig, scene_dir: Path, cams, images: dict[str, Path], out: Path):
    """Start points for the fit and what they are: the capture's COLMAP points, else SIFT
    matches triangulated with the training cameras fixed (cached in `out`), else None (random
    points in the frusta). Returns ((xyz, rgb) or None, description)."""
    if cfg.init not in ("auto", "colmap", "triangulate", "random"):
        raise DatasetError(f"fit.init={cfg.init!r}: use auto, colmap, triangulate or random")
    if cfg.init in ("auto", "colmap"):
        for sparse in (scene_dir / "sparse" / "0", scene_dir / "sparse"):
            if (sparse / "points3D.bin").is_file() or (sparse / "points3D.txt").is_file():
                xyz, rgb = read_colmap_points(sparse)
                return (xyz, rgb.astype(np.float32) / 255.0), f"colmap points ({len(xyz)})"
        if cfg.init == "colmap":
            raise DatasetError(f"{scene_dir}: fit.init=colmap but there is no sparse/ model")
    if cfg.init in ("auto", "triangulate"):
        train_idx, _ = split_views(cams, cfg.holdout_every)  # held-out views stay unseen
        train = [cams[i] for i in train_idx]
        cache = out / "init_points.npz"
        key = ",".join(c.name for c in train) + f"|seed={cfg.seed}"
        if cache.is_file():
            with np.load(cache) as z:
                if str(z["views"]) == key:
                    return (z["xyz"], z["rgb"]), f"triangulated ({len(z['xyz'])}, cached)"
        try:
            xyz, rgb, summary = triangulate_known_poses(train, images, seed=cfg.seed)
        except (ValueError, RuntimeError) as exc:  # e.g. images in several folders
            if cfg.init == "triangulate":
                raise DatasetError(f"{scene_dir}: triangulation failed: {exc}") from exc
            print(f"note: {scene_dir}: triangulation failed ({exc}); random start points")
            return None, "random in frusta"
        if len(xyz) >= 100:
            out.mkdir(parents=True, exist_ok=True)
            atomic_write_npz(cache, xyz=xyz, rgb=rgb, views=np.array(key))
            return (xyz, rgb), (
                f"triangulated ({summary['points']} points, track "
                f"{summary['mean_track_length']:.2f}, error "
                f"{summary['mean_reprojection_error_px']:.2f} px)"
            )
        if cfg.init == "triangulate":
            raise DatasetError(f"{scene_dir}: only {len(xyz)} points triangulated")
    return None, "random in frusta"


def near_depth(cams, points, bounds) -> float:
    """The nearest scene depth the capture records: LLFF's near bound, else the 2nd percentile
    of the start points' depths over the training views, else 0 (unknown)."""
    if bounds is not None:
        return bounds[0]
    if points is None:
        return 0.0
    xyz = torch.tensor(points[0], dtype=torch.float32)
    depths = [cam.project(xyz)[1] for cam in cams]
    z = torch.cat([d[d > 0] for d in depths])
    return float(torch.quantile(z, 0.02)) if z.numel() else 0.0


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


def fit_scene(cfg: DictConfig, adapter, scene: str) -> dict:
    scene_dir, cams, images = adapter.capture(scene)
    if len(images) < 2:
        raise DatasetError(
            f"{adapter.name}/{scene}: {len(images)} images with cameras; fitting needs at least two"
        )
    out = output_dir(scene_dir, adapter.name)
    foreign = foreign_scene(out)
    if not cfg.overwrite:
        if (out / "fit_metrics.json").is_file() and (out / "point_cloud.ply").is_file():
            print(f"{scene}: already fitted ({out}); pass overwrite=true to fit again")
            return {"scene": scene, "skipped": True}
        if foreign is not None:
            print(
                f"{scene}: {foreign} is a trained scene that `make scenes` did not write (no "
                "fit_metrics.json beside it); it is left as it is. Pass overwrite=true to fit "
                "anyway (it is then kept as a .bak file).",
                file=sys.stderr,
            )
            return {"scene": scene, "skipped": True}
    fit_cfg = FitConfig(**OmegaConf.to_container(cfg.fit, resolve=True))
    train_cams, train_imgs = load_images(cams, images, fit_cfg.max_side)
    bounds = near_far = None
    if (scene_dir / "poses_bounds.npy").is_file():
        b = load_llff_bounds(scene_dir)
        bounds = (float(b[:, 0].min()), float(b[:, 1].max()))
        near_far = (bounds[0] * 0.9, bounds[1] * 1.1)  # random start points: a little beyond
    points, init = initial_points(fit_cfg, scene_dir, train_cams, images, out)
    if fit_cfg.camera_clearance is None:  # auto: half the nearest depth the capture records
        fit_cfg.camera_clearance = 0.5 * near_depth(train_cams, points, bounds)
    fitter = SceneFitter(
        fit_cfg,
        train_cams,
        train_imgs,
        points,
        near_far,
        other_cameras=[c for c in cams if c.name not in images],
    )
    ckpt = out / "fit_checkpoint.pt"
    if fitter.resume(ckpt):
        print(f"{scene}: resuming at iteration {fitter.step}")
    metrics = fitter.fit(progress=cfg.progress, checkpoint=ckpt)
    metrics.update(
        {
            "scene": scene,
            "dataset": adapter.name,
            "images": len(train_imgs),
            "resolution": [train_cams[0].width, train_cams[0].height],
            "init": init,
        }
    )
    g = fitter.export()
    with torch.no_grad():
        on_device = g.to(fit_cfg.device)
        renders = {i: fitter.render(on_device, i).rgb.clamp(0, 1).cpu() for i in fitter.held_idx}
    metrics["psnr_heldout_object"] = object_psnr(adapter, scene, fitter, renders)
    if foreign is not None:  # overwrite=true: keep the user's scene beside ours
        backup = foreign.with_name(f"{foreign.name}.bak-{time.strftime('%Y%m%d-%H%M%S')}")
        foreign.rename(backup)
        print(f"{scene}: the scene that was there is now {backup}")
    write_fitted_scene(out, fitter, cams, metrics)
    for i, render in renders.items():
        pair = np.concatenate([render.numpy(), train_imgs[i].numpy()], axis=1)
        atomic_write_image(
            out / f"heldout_{train_cams[i].name}.png", (pair * 255 + 0.5).astype(np.uint8)
        )
    ckpt.unlink(missing_ok=True)
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
    return metrics


register_schemas()


@hydra.main(version_base="1.3", config_path="../conf", config_name="scenes")
def main(cfg: DictConfig) -> None:
    try:
        adapter = instantiate(cfg.dataset.adapter)
        names = [cfg.scene] if cfg.scene else adapter.scene_names()
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if not hasattr(adapter, "capture"):
        print(
            f"error: dataset {cfg.dataset.name} has no captured images to fit "
            "(the synthetic scenes are generated, not fitted)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    failed = []
    for scene in names:
        try:
            fit_scene(cfg, adapter, scene)
        except DatasetError as exc:
            print(f"error: {scene}: {exc}", file=sys.stderr)
            failed.append(scene)
    if failed:
        raise SystemExit(2)


if __name__ == "__main__":
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    main()
