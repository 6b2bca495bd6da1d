"""A fit's last steps and what it writes: the co-pruning against a second draw, the carve and
their polish after the last iteration (`FitConfig.co_prune_seed`, `carve_views`), a finished
fit taken up again as the state after its last iteration (`make scenes finish_from=`), and the
fitted scene's folder. `fitter` is a `trainer.SceneFitter` (not imported: the trainer imports
this module)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from sagonline.core.files import atomic_write_json
from sagonline.core.provenance import digest_file
from sagonline.fitting.strategy import keep_only, looked_through
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.io import write_ply
from sagonline.scene.io.cameras import write_3dgs_cameras_json


def carve_and_polish(fitter) -> None:
    """With a second draw's centres (`fitter.partner_means`, `co_prune_seed`), the co-pruning;
    with `carve_views`, the carve; after either or with `polish_opacity_entropy`, the polish
    (the opacities' entropy in its loss where weighted), then the faded Gaussians dropped."""
    cfg = fitter.cfg
    partner = getattr(fitter, "partner_means", None)
    if partner is not None:
        fitter.co_pruned = co_prune(fitter, partner)
    if cfg.carve_views > 0:
        fitter.carved = carve(fitter)
    if cfg.carve_views > 0 or cfg.polish_opacity_entropy > 0 or partner is not None:
        fitter.polishing = True
        polish(fitter, cfg.polish_iterations)
        fitter.polishing = False
    if cfg.polish_opacity_entropy > 0:
        fitter.faded = prune_faded(fitter)


@torch.no_grad()
def carve(fitter) -> int:
    """Drop the Gaussians at least `carve_views` training photographs look through
    (`strategy.looked_through`, against the fit's own render of each); returns how many."""
    cfg = fitter.cfg
    g = fitter.gaussians()
    means = g.means.detach()
    through = torch.zeros(len(fitter), dtype=torch.long, device=means.device)
    for i in fitter.train_idx:
        out = fitter.render(g, i)
        through += looked_through(
            means, fitter.cams[i], out.alpha, out.depth, cfg.carve_margin
        ).long()
    params, dropped = keep_only(fitter.params, through < cfg.carve_views)
    if params is not None:
        fitter._set_params(params)
    return dropped


def nearest_distances(
    points: torch.Tensor,  # [N, 3]
    others: torch.Tensor,  # [M, 3]
    chunk: int = 1024,
) -> torch.Tensor:  # [N]
    """Each point's distance to the nearest of `others` (in chunks of `chunk` points)."""
    if len(others) == 0:
        return torch.full((len(points),), float("inf"), device=points.device)
    parts = [
        torch.cdist(points[i : i + chunk], others).amin(dim=1) for i in range(0, len(points), chunk)
    ]
    return torch.cat(parts) if parts else points.new_zeros(0)


@torch.no_grad()
def co_prune(fitter, partner: torch.Tensor) -> int:  # partner [M, 3]
    """Drop the Gaussians with no centre of `partner` (a second draw's) within
    `co_prune_sigmas` of their largest scale; returns how many."""
    means = fitter.params["means"].detach()
    reach = fitter.cfg.co_prune_sigmas * fitter.params["log_scales"].detach().exp().amax(dim=1)
    near = nearest_distances(means, partner.to(means.device, means.dtype)) <= reach
    params, dropped = keep_only(fitter.params, near)
    if params is not None:
        fitter._set_params(params)
    return dropped


def polish(fitter, iterations: int) -> None:
    """Train `iterations` more steps on the training views (in an order of their own, seeded
    by the fit's seed), without densification, positions at their last learning rate."""
    rng = np.random.default_rng([fitter.cfg.seed, iterations])
    for _ in range(iterations):
        fitter.train_step(fitter.train_idx[int(rng.integers(len(fitter.train_idx)))], 1.0)


@torch.no_grad()
def prune_faded(fitter) -> int:
    """Drop the Gaussians whose opacity is below `prune_opacity`; returns how many."""
    opacity = torch.sigmoid(fitter.params["opacity_logit"]).reshape(len(fitter))
    params, dropped = keep_only(fitter.params, opacity >= fitter.cfg.prune_opacity)
    if params is not None:
        fitter._set_params(params)
    return dropped


def adopt_finished(fitter, g: Gaussians) -> None:
    """Take a finished fit of this recipe (its written scene) as the state after the last
    iteration: `fitter.fit` then runs only the steps after it (`SceneFitter.finish`)."""
    d = fitter.cfg.device

    def raw(t: torch.Tensor) -> torch.Tensor:
        return t.detach().to(d, torch.float32).contiguous()

    fitter._set_params(
        {
            "means": raw(g.means).clone(),
            "log_scales": torch.log(raw(g.scales)),
            "quats": raw(g.quats).clone(),
            "opacity_logit": torch.logit(raw(g.opacities)),
            "sh_dc": raw(g.sh[:, :1]),
            "sh_rest": raw(g.sh[:, 1:]),
        }
    )
    fitter.step, fitter.finished = fitter.cfg.iterations, False


def write_fitted_scene(out_dir: Path, fitter, all_cameras: list[Camera], metrics: dict) -> Path:
    """point_cloud.ply + cameras.json (every camera of the scene) + fit_config.json +
    fit_metrics.json into `out_dir` (the dataset adapter's `gaussians/` folder)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = write_ply(out_dir / "point_cloud.ply", fitter.export())
    write_3dgs_cameras_json(out_dir / "cameras.json", all_cameras)
    atomic_write_json(out_dir / "fit_config.json", asdict(fitter.cfg))
    # the digest marks the scene as ours: `make scenes` replaces only a file that matches it
    metrics = {**metrics, "scene_digest": digest_file(scene)}
    atomic_write_json(out_dir / "fit_metrics.json", metrics)
    return out_dir / "point_cloud.ply"
