"""The fitting loop: raw parameters, Adam, the schedule, evaluation and checkpoints. It knows
nothing of datasets: cameras, images and optional start points come in, a scene goes out.

Parameters in raw form (log scales, opacity logits, unnormalised quaternions, SH split into
degree 0 and the rest), Adam with the 3DGS learning rates (positions scaled by the scene extent
and decayed exponentially, higher SH degrees at 1/20 of degree 0), the loss of
`losses.photometric_loss` (plus the optional needle penalty and 2DGS's depth-distortion and
normal-consistency regularisers, composited through the same rasterizer), densification by
`strategy.DensifyStrategy`. Every 8th view (sorted by name) is held out and scored by PSNR.

On CPU the rasterizer is this library's own: the compiled kernel with its hand-written backward
(`render.native`; `backend: auto` picks it), or autograd through the tiled PyTorch path
(`backend: torch`, same values, slower); on CUDA `backend: auto` renders through gsplat, whose
2DGS and 3DGS rasterization is differentiable there. Simplifications against the 2DGS reference,
stated here once: the positional gradient is taken in world space (scaled by depth to pixels)
rather than on the projected means, the optimiser state of new Gaussians starts at zero, all SH
degrees train from the start, and the depth distortion is taken over splat-centre depths (the
2DGS kernel uses each ray's intersection depth).

A step reads nothing back on the host: its loss, regularisers and PSNR stay on the device until
`history` or `last_terms` is read (every 10th step, for the progress bar), so on a GPU the host
queues the next steps while the kernels run (bench/speed/host_work.py counts what a step asks of
the host). Checkpoints: `fitting.checkpoint`.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sagonline.core.progress import Progress
from sagonline.fitting.capture import training_background
from sagonline.fitting.checkpoint import resume_checkpoint, save_checkpoint
from sagonline.fitting.config import FitConfig
from sagonline.fitting.depth_prior import MonocularDepth, prior_term, pseudo_view_term
from sagonline.fitting.finish import carve_and_polish
from sagonline.fitting.losses import (
    ReadLater,
    anisotropy_penalty,
    depth_distortion,
    mse,
    nearest_views,
    neighbour_consistency,
    normal_consistency,
    opacity_entropy,
    photometric_loss,
    psnr,
    psnr_from_mse,
    splat_geometry,
)
from sagonline.fitting.start_points import initial_params, split_views, start_points, view_draws
from sagonline.fitting.strategy import DensifyStrategy, Params
from sagonline.fitting.threads import on_one_torch_thread
from sagonline.render.api import render
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians


class SceneFitter:
    """Holds the raw parameters and the optimiser; `fit` runs (or resumes) the schedule.
    images: (H, W, 3) floats in [0, 1], one per camera; points: optional (xyz, rgb) start points;
    other_cameras: cameras of the capture without an image (kept clear like the others);
    view_near: the nearest depth the capture records per view name (for `view_clearance`)."""

    @on_one_torch_thread
    def __init__(
        self,
        cfg: FitConfig,
        cameras: list[Camera],
        images: list[torch.Tensor],
        points: tuple[np.ndarray, np.ndarray] | None = None,
        near_far: tuple[float, float] | None = None,
        other_cameras: list[Camera] = (),
        view_near: dict[str, float] | None = None,
    ):
        if cfg.kind not in ("2dgs", "3dgs"):
            raise ValueError(f"fit kind {cfg.kind!r} is not '2dgs' or '3dgs'")
        if len(cameras) != len(images) or len(cameras) < 2:
            raise ValueError("fitting needs at least two posed images")
        for cam, img in zip(cameras, images, strict=True):
            if tuple(img.shape) != (cam.height, cam.width, 3):
                raise ValueError(
                    f"image of view {cam.name} is {tuple(img.shape)}, its camera "
                    f"{cam.height}x{cam.width}"
                )
        self.cfg, self.images = cfg, [i.to(cfg.device) for i in images]
        self.cams = [c.to(cfg.device) for c in cameras]
        self.train_idx, self.held_idx = split_views(cameras, cfg.holdout_every, cfg.train_every)
        rng = np.random.default_rng(cfg.seed)
        centers = torch.stack([c.center for c in cameras]).double()
        self.extent = float((centers - centers.mean(0)).norm(dim=1).max()) * 1.1 or 1.0
        if near_far is None:
            dist = float((centers - centers.mean(0)).norm(dim=1).mean())
            near_far = (0.2 * dist, 2.0 * dist)
        self.near_far = near_far
        xyz, rgb = start_points(
            [cameras[i] for i in self.train_idx],
            [images[i] for i in self.train_idx],
            points,
            near_far,
            cfg.init_points,
            cfg.background_points,
            rng,
        )
        # nothing of the scene sits closer than `camera_clearance` to any camera of the capture
        # (training ones and those without an image): Gaussians there are floaters that no
        # training view constrains yet every nearby novel view looks through
        every_camera = [*cameras, *other_cameras]
        every_center = torch.stack([c.center for c in every_camera])
        if cfg.view_clearance_views not in ("train", "all"):
            raise ValueError(
                f"fit.view_clearance_views={cfg.view_clearance_views!r}: use train or all"
            )
        near = view_near or {}
        views = (
            [cameras[i] for i in self.train_idx]
            if cfg.view_clearance_views == "train"
            else every_camera
        )
        self.strategy = DensifyStrategy(
            cfg,
            every_center,
            self.extent,
            views=views,
            view_near=[near.get(c.name, 0.0) for c in views],
            pose_views=[(c, near.get(c.name, 0.0)) for c in other_cameras],
        )
        clear = self.strategy.clear_of_cameras(torch.tensor(xyz, dtype=torch.float32))
        clear = clear.cpu().numpy()
        self._init_params(xyz[clear], rgb[clear], rng)
        train = self.train_idx  # each training photograph's 2 nearest, for `lambda_warp`
        closest = nearest_views([self.cams[i] for i in train])
        self.neighbours = {v: [train[j] for j in closest[i]] for i, v in enumerate(train)}
        self.depth_priors, self.depth_model = {}, None  # [H, W] per training view
        if cfg.lambda_depth > 0:
            self.depth_model = MonocularDepth(cfg.depth_model)
            self.depth_priors = {i: self.depth_model(self.images[i]) for i in train}
        self.step, self.losses, self.elapsed = 0, ReadLater(), 0.0  # the loss at each step
        self.finished = False  # the steps after the last iteration ran (`finish`)
        self.polishing = False  # in the polish (`finish`): its own loss terms apply
        self.faded = 0  # Gaussians dropped below `prune_opacity` after the polish
        self.carved = self.co_pruned = 0  # Gaussians the carve and the co-pruning dropped
        self.partner_means = None  # [M, 3] a second draw's centres, for `co_prune_seed`
        self.terms: dict[str, torch.Tensor] = {}  # the regularisers' values at the last step
        self.stopped = "iterations"  # or "time_budget": the fit ended on its wall-clock budget

    # --- parameters ---------------------------------------------------------------------------
    def _init_params(self, xyz: np.ndarray, rgb: np.ndarray, rng) -> None:
        cfg = self.cfg
        self._set_params(initial_params(xyz, rgb, cfg.kind, cfg.sh_degree, rng, cfg.device))

    def _set_params(self, params: Params) -> None:
        """Adopt a new parameter set: a fresh optimiser and fresh gradient statistics."""
        cfg = self.cfg
        self.params = params
        for p in params.values():
            p.requires_grad_(True)
        lrs = {
            "means": cfg.lr_means * self.extent,
            "log_scales": cfg.lr_scales,
            "quats": cfg.lr_quats,
            "opacity_logit": cfg.lr_opacity,
            "sh_dc": cfg.lr_sh,
            "sh_rest": cfg.lr_sh / 20,
        }
        groups = [{"params": [params[k]], "lr": lr, "name": k} for k, lr in lrs.items()]
        # on CUDA one kernel a group (fused); on the CPU PyTorch's default, as the fits had
        fused = True if self.params["means"].is_cuda else None
        self.optim = torch.optim.Adam(groups, eps=1e-15, fused=fused)
        self.strategy.reset(len(self))

    @property
    def history(self) -> list[float]:
        """The training loss of every step so far."""
        return self.losses.values()

    @property
    def last_terms(self) -> dict[str, float]:
        """The regularisers' values at the last step."""
        return {k: float(v) for k, v in self.terms.items()}

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def camera_centers(self) -> torch.Tensor:  # [C, 3]
        """(C, 3) centres of every camera of the capture."""
        return self.strategy.camera_centers

    def gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians(
            means=p["means"],
            quats=F.normalize(p["quats"], dim=1),
            scales=torch.exp(p["log_scales"]),
            opacities=torch.sigmoid(p["opacity_logit"]),
            sh=torch.cat([p["sh_dc"], p["sh_rest"]], dim=1),
        )

    @on_one_torch_thread
    def export(self) -> Gaussians:
        """The fitted scene on the CPU, detached."""
        g = self.gaussians()
        return Gaussians(
            **{
                k: getattr(g, k).detach().cpu()
                for k in ("means", "quats", "scales", "opacities", "sh")
            }
        )

    def render(
        self,
        gaussians: Gaussians,
        view: int,
        features: torch.Tensor | None = None,  # [N, F] composited beside RGB
        background: torch.Tensor | None = None,  # [3]; None: the fit's `background`
    ):
        """Render training view `view` as the fit sees it (its background and backend)."""
        bg = torch.tensor(self.cfg.background) if background is None else background
        bg, cam = bg.to(self.cfg.device), self.cams[view]
        return render(gaussians, cam, background=bg, backend=self.cfg.backend, features=features)

    def loss(
        self,
        gaussians: Gaussians,
        view: int,
    ) -> tuple[torch.Tensor, torch.Tensor, dict]:  # [] loss, [H, W, 3] render, values
        """The training loss of one view, its render (H, W, 3) and the regularisers' values
        (detached, on the device)."""
        cfg, cam = self.cfg, self.cams[view]
        use_dist = cfg.lambda_dist > 0 and self.step >= cfg.dist_from
        use_normal = cfg.lambda_normal > 0 and self.step >= cfg.normal_from
        geometry = None
        if use_dist or use_normal:
            geometry = splat_geometry(gaussians, cam, *self.near_far)
        bg = training_background(cfg, self.step)
        out = self.render(gaussians, view, features=geometry, background=bg)
        trim = cfg.robust_trim if self.step >= cfg.robust_from else 0.0
        loss = photometric_loss(out.rgb, self.images[view], cfg.lambda_dssim, trim)
        terms = {}
        if cfg.lambda_aniso:
            loss = loss + cfg.lambda_aniso * self.anisotropy_penalty()
        if self.polishing and cfg.polish_opacity_entropy:
            terms["entropy"] = opacity_entropy(self.params["opacity_logit"])
            loss = loss + cfg.polish_opacity_entropy * terms["entropy"]
        if use_dist:
            terms["dist"] = depth_distortion(out.alpha, out.features[..., 3], out.features[..., 4])
            loss = loss + cfg.lambda_dist * terms["dist"]
        if use_normal:
            terms["normal"] = normal_consistency(out.features[..., :3], out.depth, out.alpha, cam)
            loss = loss + cfg.lambda_normal * terms["normal"]
        if cfg.lambda_warp > 0 and self.step >= cfg.warp_from:
            others = [(self.cams[j], self.images[j]) for j in self.neighbours[view]]
            terms["warp"] = neighbour_consistency(
                out.depth, out.alpha, self.images[view], cam, others
            )
            loss = loss + cfg.lambda_warp * terms["warp"]
        if cfg.lambda_depth > 0:
            terms["depth"] = prior_term(cfg, out, self.depth_priors[view])
            loss = loss + cfg.lambda_depth * terms["depth"]
        pseudo = pseudo_view_term(self, gaussians)
        if pseudo is not None:
            terms["pseudo_depth"] = pseudo
            loss = loss + cfg.lambda_depth * pseudo
        return loss, out.rgb, {k: v.detach() for k, v in terms.items()}

    def anisotropy_penalty(self) -> torch.Tensor:  # []
        return anisotropy_penalty(self.params["log_scales"], self.cfg.max_aspect)

    def prune_near_cameras(self) -> int:
        """Drop Gaussians inside the camera clearance; returns how many."""
        params, dropped = self.strategy.prune_near_cameras(self.params)
        if params is not None:
            self._set_params(params)
        return dropped

    # --- the loop -----------------------------------------------------------------------------
    @on_one_torch_thread
    def fit(self, progress: bool = True, checkpoint: Path | None = None) -> dict:
        """Train to `cfg.iterations` (or the time budget); returns `evaluate()`'s metrics."""
        cfg = self.cfg
        rng = view_draws(cfg.seed, self.step, len(self.train_idx))
        bar = Progress("fit", cfg.iterations, enabled=progress, initial=self.step)
        start = time.perf_counter() - self.elapsed
        recent_mse = deque(maxlen=10)  # training-view MSE of the last steps, for the bar
        while self.step < cfg.iterations:
            if cfg.time_budget_s is not None and time.perf_counter() - start > cfg.time_budget_s:
                self.stopped = "time_budget"
                break
            i = self.train_idx[int(rng.integers(len(self.train_idx)))]
            rgb = self.train_step(i, self.step / max(cfg.iterations, 1))
            self.step += 1
            recent_mse.append(mse(rgb.clamp(0, 1), self.images[i]))
            changed = self.strategy.after_step(self.params, self.step)
            if changed is not None:
                self._set_params(changed)
            detail = ""
            if self.step % 10 == 0:  # the host reads the GPU's values here, not every step
                psnrs = [psnr_from_mse(v) for v in torch.stack(list(recent_mse)).tolist()]
                detail = ", ".join(
                    [
                        f"loss {np.mean(self.history[-10:]):.4f}",
                        f"PSNR {np.mean(psnrs):.2f} dB",
                        f"{len(self)} Gaussians",
                        *(f"{k} {v:.2e}" for k, v in self.last_terms.items()),
                    ]
                )
            bar.update(1, detail)
            if checkpoint is not None and self.step % cfg.checkpoint_every == 0:
                self.elapsed = time.perf_counter() - start
                self.save(checkpoint)
        bar.close()
        if not self.finished:
            self.finish()
        self.elapsed = time.perf_counter() - start
        if checkpoint is not None:
            self.save(checkpoint)
        return self.evaluate()

    def train_step(self, view: int, progress: float) -> torch.Tensor:  # [H, W, 3] render
        """One optimiser step on training view `view`, the positions' learning rate decayed
        to `progress` (0-1) of the schedule; its render (H, W, 3, detached). Its loss and terms
        stay on the device (`history` and `last_terms` read them)."""
        cfg = self.cfg
        for group in self.optim.param_groups:
            if group["name"] == "means":
                group["lr"] = cfg.lr_means * self.extent * (0.01 ** min(progress, 1.0))
        loss, rgb, self.terms = self.loss(self.gaussians(), view)
        self.optim.zero_grad(set_to_none=True)
        loss.backward()
        self.strategy.after_backward(self.params, self.cams[view])
        self.optim.step()
        self.losses.append(loss)
        return rgb.detach()

    def finish(self) -> None:
        """The steps after the last iteration: the camera and pose-view clearances, then the
        carve and the polish (`finish.carve_and_polish`). Run once (a resumed fit that finished
        skips them)."""
        self.prune_near_cameras()
        params, self.pruned_pose_views = self.strategy.prune_pose_views(self.params)
        if params is not None:
            self._set_params(params)
        carve_and_polish(self)
        self.finished = True

    @torch.no_grad()
    @on_one_torch_thread
    def evaluate(self) -> dict:
        g = self.gaussians()

        def mean_psnr(ids):
            vals = [psnr(self.render(g, i).rgb.clamp(0, 1), self.images[i]) for i in ids]
            return float(np.mean(vals)) if vals else None

        return {
            "psnr_train": mean_psnr(self.train_idx),
            "psnr_heldout": mean_psnr(self.held_idx),
            "gaussians": len(self),
            "iterations": self.step,
            "iterations_planned": self.cfg.iterations,
            "stopped": self.stopped,
            "pruned_pose_views": getattr(self, "pruned_pose_views", 0),
            "carved": self.carved,
            "co_pruned": self.co_pruned,
            "faded": self.faded,
            "depth_model_sha256": self.depth_model and self.depth_model.sha256,  # or None
            "fit_seconds": round(self.elapsed, 1),
            "heldout_views": [self.cams[i].name for i in self.held_idx],
            "train_views": len(self.train_idx),  # fewer than the rest with fit.train_every > 1
            "final_loss": float(np.mean(self.history[-20:])) if self.history else None,
            "final_regularisers": self.last_terms,
        }

    # --- checkpoints --------------------------------------------------------------------------
    def save(self, path: Path) -> None:
        save_checkpoint(self, path)

    def resume(self, path: Path) -> bool:
        """Continue an interrupted fit with the same settings (`checkpoint.resume_checkpoint`);
        False if there is none or it cannot serve."""
        return resume_checkpoint(self, path)
