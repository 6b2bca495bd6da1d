"""Fit the Gaussian scene a dataset needs: `make scenes DATASET=<name> [SCENE=<scene>]`.

For each scene: read its images and cameras, downsample to `fit.max_side`, initialise from
COLMAP points where the capture has them (random points in the training frusta otherwise),
fit (sagonline.fit), and write point_cloud.ply + cameras.json + fit_config.json +
fit_metrics.json where the dataset adapter looks (`<scene>/gaussians/`, or
`scenes/<dataset>/<scene>/gaussians/` when the data folder is read-only), with side-by-side
renders of the held-out views to look at. Interrupted fits resume from fit_checkpoint.pt.
"""

from __future__ import annotations

import os
import stat
import sys
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from PIL import Image

from sagonline.cameras import load_llff_bounds, read_colmap_points
from sagonline.datasets.base import DatasetError
from sagonline.datasets.common import SCENES_ROOT
from sagonline.fit import FitConfig, SceneFitter, write_fitted_scene
from sagonline.render.rasterize import rasterize
from sagonline.utils import atomic_write_image


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


def fit_scene(cfg: DictConfig, adapter, scene: str) -> dict:
    scene_dir, cams, images = adapter.capture(scene)
    if len(images) < 2:
        raise DatasetError(
            f"{adapter.name}/{scene}: {len(images)} images with cameras; fitting needs at least two"
        )
    fit_d = OmegaConf.to_container(cfg.fit, resolve=True)
    max_side = fit_d.pop("max_side")
    fit_cfg = FitConfig(**fit_d)
    train_cams, train_imgs = load_images(cams, images, max_side)
    points = None
    for sparse in (scene_dir / "sparse" / "0", scene_dir / "sparse"):
        if (sparse / "points3D.bin").is_file() or (sparse / "points3D.txt").is_file():
            xyz, rgb = read_colmap_points(sparse)
            points = (xyz, rgb.astype(np.float32) / 255.0)
            break
    near_far = None
    if (scene_dir / "poses_bounds.npy").is_file():
        b = load_llff_bounds(scene_dir)
        near_far = (float(b[:, 0].min()) * 0.9, float(b[:, 1].max()) * 1.1)
    out = output_dir(scene_dir, adapter.name)
    done = out / "fit_metrics.json"
    if done.is_file() and (out / "point_cloud.ply").is_file() and not cfg.overwrite:
        print(f"{scene}: already fitted ({out}); pass overwrite=true to fit again")
        return {"scene": scene, "skipped": True}
    fitter = SceneFitter(fit_cfg, train_cams, train_imgs, points, near_far)
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
            "init": "colmap points" if points is not None else "random in frusta",
        }
    )
    write_fitted_scene(out, fitter, cams, metrics)
    g = fitter.export()
    for i in fitter.held_idx:
        render = rasterize(g, train_cams[i]).rgb.clamp(0, 1).numpy()
        pair = np.concatenate([render, train_imgs[i].numpy()], axis=1)
        atomic_write_image(
            out / f"heldout_{train_cams[i].name}.png", (pair * 255 + 0.5).astype(np.uint8)
        )
    ckpt.unlink(missing_ok=True)
    print(
        f"{scene}: PSNR train {metrics['psnr_train']:.2f} dB, held-out "
        f"{metrics['psnr_heldout']:.2f} dB, {metrics['gaussians']} Gaussians, "
        f"{metrics['fit_seconds']:.0f} s -> {out}"
    )
    return metrics


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
