"""Fit a Gaussian scene (2DGS by default, 3DGS as an option) to posed images.

The same recipe every time: parameters in raw form (log scales, opacity logits, unnormalised
quaternions, SH split into degree 0 and the rest), Adam with the 3DGS learning rates (positions
scaled by the scene extent and decayed exponentially, higher SH degrees at 1/20 of degree 0),
loss (1 - lambda) L1 + lambda (1 - SSIM) with lambda = 0.2 (plus an optional needle penalty on
axis ratios, off by default), and the 3DGS densification schedule: every `densify_every`
iterations between `densify_from` and `densify_until`, Gaussians whose accumulated positional
gradient exceeds `grad_threshold` are cloned (small) or split in two (large), and nearly
transparent ones (opacity < 0.005) are pruned (after the first opacity reset also those wider
than a tenth of the scene); opacities are reset every `opacity_reset_every` iterations.
Gaussians closer than `camera_clearance` to any camera of the capture are pruned at the start,
at every densification step and at the end. Every 8th view (sorted by name) is held out and
scored by PSNR.

On CPU the rasterizer is this library's own: the compiled kernel with its hand-written backward
(`render.native`, `backend: auto`), or autograd through the tiled PyTorch path
(`backend: torch`, same values, slower), meant for small scenes and tests; on CUDA
(`backend: auto`) the same loop renders through gsplat, whose 2DGS and 3DGS rasterization is
differentiable there. Simplifications against the 2DGS reference, stated here once: the
positional gradient is taken in world space (scaled by depth over focal length to pixels)
rather than on the projected means, the optimiser state of new Gaussians starts at zero, all SH
degrees train from the start, and 2DGS's depth-distortion and normal-consistency regularisers
are not used.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from sagonline.cameras import Camera
from sagonline.gaussians import SH_C0, Gaussians
from sagonline.io import write_ply
from sagonline.render.api import render
from sagonline.utils import atomic_write


@dataclass
class FitConfig:
    kind: str = "2dgs"
    init: str = "auto"  # auto: COLMAP points, else triangulated (poses fixed), else random
    background_points: int = 5000  # random points in the frusta added to a sparse-point start
    max_side: int = 228  # images downsampled so the longer side is at most this (`make scenes`)
    iterations: int = 3000  # the paper trains 30k on a GPU; CPU fits are for small scenes
    sh_degree: int = 3
    init_points: int = 15000
    lambda_dssim: float = 0.2
    lambda_aniso: float = 0.0  # weight of the needle penalty (see `anisotropy_penalty`)
    max_aspect: float = 10.0  # longest / shortest axis allowed before the penalty starts
    lr_means: float = 1.6e-4  # times the scene extent, decayed to 1% by the end
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh: float = 2.5e-3  # degree 0; higher degrees learn 20x slower (as 3DGS)
    # prune Gaussians this close to any camera centre; 0: off; None: the caller's automatic
    # value (`make scenes`: half the nearest recorded depth), off when none is given
    camera_clearance: float | None = None
    densify_from: int = 200
    densify_until: int = 1500
    densify_every: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    max_gaussians: int = 40_000
    opacity_reset_every: int = 1000
    prune_opacity: float = 0.005
    holdout_every: int = 8
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    checkpoint_every: int = 100
    time_budget_s: float | None = None  # seconds; None: bounded by iterations alone
    seed: int = 0
    device: str = "cpu"
    backend: str = "auto"  # auto: gsplat on CUDA when installed, else the PyTorch rasterizer


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two (H, W, 3) images in [0, 1] (Gaussian window, the usual constants)."""
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    g = torch.exp(-((torch.arange(window, device=a.device) - window // 2) ** 2) / (2 * sigma**2))
    g = (g / g.sum()).to(a.dtype)
    k = (g[:, None] * g[None, :]).expand(3, 1, window, window)
    pad = window // 2

    def blur(t):
        return F.conv2d(t, k, padding=pad, groups=3)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    return s.mean()


def psnr_from_mse(mse: float) -> float:
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return psnr_from_mse(float(((a - b) ** 2).mean()))


def split_views(cameras: list[Camera], every: int) -> tuple[list[int], list[int]]:
    """Indices of training and held-out views: every `every`-th (sorted by name) is held out."""
    order = sorted(range(len(cameras)), key=lambda i: cameras[i].name)
    held = [i for k, i in enumerate(order) if every and k % every == 0]
    return [i for i in order if i not in held], held


def init_from_views(
    cameras: list[Camera],
    images: list[torch.Tensor],
    count: int,
    near_far: tuple[float, float],
    rng: np.random.Generator,
    min_visible: float = 0.5,
    near_per_view: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Random points in the training frusta: a random pixel of a random view at a random
    (log-uniform) depth between near and far, coloured by that pixel, kept when at least
    `min_visible` of the views see it (for orbits: the region they all look at; a fallback
    keeps the most visible candidates; 0 keeps every point). `near_per_view` (V,) replaces
    `near` per view. (P, 3) xyz, (P, 3) rgb in [0, 1]."""
    near, far = near_far
    m = 8 * count if min_visible > 0 else count
    views = rng.integers(len(cameras), size=m)
    u, v = rng.uniform(0, 1, m), rng.uniform(0, 1, m)
    lo = np.full(m, math.log(near)) if near_per_view is None else np.log(near_per_view[views])
    depth = np.exp(rng.uniform(lo, math.log(far)))
    xyz, rgb = np.empty((m, 3)), np.empty((m, 3))
    for i in range(len(cameras)):
        sel = views == i
        cam, img = cameras[i], images[i]
        px, py = u[sel] * cam.width, v[sel] * cam.height
        rays = np.stack([px, py, np.ones_like(px)], 1) @ np.linalg.inv(cam.K.double().numpy()).T
        p_cam = rays * depth[sel, None]
        R, t = cam.rotation.double().numpy(), cam.translation.double().numpy()
        xyz[sel] = (p_cam - t) @ R
        rgb[sel] = (
            img[py.astype(int).clip(0, cam.height - 1), px.astype(int).clip(0, cam.width - 1)]
            .cpu()
            .numpy()
        )
    if min_visible <= 0:
        return xyz, rgb
    pts = torch.tensor(xyz, dtype=torch.float32)
    seen = np.zeros(m)
    for cam in cameras:
        seen += cam.in_frame(pts)[0].numpy()
    order = np.argsort(-seen, kind="stable")
    keep = order[seen[order] >= min_visible * len(cameras)][:count]
    if len(keep) < count // 2:
        keep = order[:count]
    return xyz[keep], rgb[keep]


def _median_depth(cam: Camera, xyz: np.ndarray, default: float) -> float:
    """Median camera depth of the points `cam` sees (`default` when it sees none)."""
    seen, z = cam.in_frame(torch.tensor(xyz, dtype=torch.float32))
    return float(z[seen].median()) if bool(seen.any()) else default


class SceneFitter:
    """Holds the raw parameters and the optimiser; `fit` runs (or resumes) the schedule."""

    def __init__(
        self,
        cfg: FitConfig,
        cameras: list[Camera],
        images: list[torch.Tensor],
        points: tuple[np.ndarray, np.ndarray] | None = None,
        near_far: tuple[float, float] | None = None,
        other_cameras: list[Camera] = (),
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
        self.train_idx, self.held_idx = split_views(cameras, cfg.holdout_every)
        rng = np.random.default_rng(cfg.seed)
        centers = torch.stack([c.center for c in cameras]).double()
        self.extent = float((centers - centers.mean(0)).norm(dim=1).max()) * 1.1 or 1.0
        if near_far is None:
            dist = float((centers - centers.mean(0)).norm(dim=1).mean())
            near_far = (0.2 * dist, 2.0 * dist)
        train_cams = [cameras[i] for i in self.train_idx]
        train_imgs = [images[i] for i in self.train_idx]
        if points is None or len(points[0]) == 0:
            points = init_from_views(train_cams, train_imgs, cfg.init_points, near_far, rng)
        elif cfg.background_points:
            # sparse points sit on textured surfaces; what they miss (walls, floor, sky) gets
            # random points in the training frusta, behind what the points already explain
            # (random points in front of the surfaces would start as floaters)
            behind = np.array([_median_depth(c, points[0], near_far[0]) for c in train_cams])
            extra = init_from_views(
                train_cams,
                train_imgs,
                cfg.background_points,
                near_far,
                rng,
                min_visible=0.0,
                near_per_view=np.minimum(behind, near_far[1] * 0.99),
            )
            points = tuple(np.concatenate([a, b]) for a, b in zip(points, extra, strict=True))
        # nothing of the scene sits closer than `camera_clearance` to any camera of the capture
        # (training ones and those without an image): Gaussians there are floaters that no
        # training view constrains yet every nearby novel view looks through
        self.camera_centers = torch.stack([c.center for c in [*cameras, *other_cameras]]).to(
            cfg.device, torch.float32
        )
        clear = self._clear_of_cameras(torch.tensor(points[0], dtype=torch.float32)).cpu().numpy()
        self._init_params(points[0][clear], points[1][clear], rng)
        self.step, self.history, self.elapsed = 0, [], 0.0
        self.stopped = "iterations"  # or "time_budget": the fit ended on its wall-clock budget

    # --- parameters ---------------------------------------------------------------------------
    def _init_params(self, xyz: np.ndarray, rgb: np.ndarray, rng) -> None:
        dev = self.cfg.device
        n = len(xyz)
        means = torch.tensor(xyz, dtype=torch.float32, device=dev)
        # initial scale: distance to the 3 nearest neighbours (as 3DGS), in log space
        from scipy.spatial import cKDTree

        d, _ = cKDTree(xyz).query(xyz, k=min(4, n))
        d = np.sqrt(np.mean(np.asarray(d).reshape(n, -1)[:, 1:] ** 2, axis=1)).clip(1e-7)
        dims = 2 if self.cfg.kind == "2dgs" else 3
        k = (self.cfg.sh_degree + 1) ** 2
        sh = torch.zeros(n, k, 3, device=dev)
        sh[:, 0] = (torch.tensor(rgb, dtype=torch.float32, device=dev) - 0.5) / SH_C0
        quats = torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32, device=dev)
        self.params = {
            "means": means,
            "log_scales": torch.log(torch.tensor(d, dtype=torch.float32, device=dev))[
                :, None
            ].repeat(1, dims),
            "quats": quats / quats.norm(dim=1, keepdim=True),
            "opacity_logit": torch.full((n,), math.log(0.1 / 0.9), device=dev),
            "sh_dc": sh[:, :1].contiguous(),
            "sh_rest": sh[:, 1:].contiguous(),
        }
        self._new_optimizer()

    def _new_optimizer(self) -> None:
        cfg = self.cfg
        for p in self.params.values():
            p.requires_grad_(True)
        lrs = {
            "means": cfg.lr_means * self.extent,
            "log_scales": cfg.lr_scales,
            "quats": cfg.lr_quats,
            "opacity_logit": cfg.lr_opacity,
            "sh_dc": cfg.lr_sh,
            "sh_rest": cfg.lr_sh / 20,
        }
        self.optim = torch.optim.Adam(
            [{"params": [self.params[k]], "lr": lr, "name": k} for k, lr in lrs.items()], eps=1e-15
        )
        self.grad_accum = torch.zeros(len(self), device=cfg.device)
        self.grad_count = torch.zeros(len(self), device=cfg.device)

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    def gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians(
            means=p["means"],
            quats=F.normalize(p["quats"], dim=1),
            scales=torch.exp(p["log_scales"]),
            opacities=torch.sigmoid(p["opacity_logit"]),
            sh=torch.cat([p["sh_dc"], p["sh_rest"]], dim=1),
        )

    def export(self) -> Gaussians:
        g = self.gaussians()
        return Gaussians(
            **{
                k: getattr(g, k).detach().cpu()
                for k in ("means", "quats", "scales", "opacities", "sh")
            }
        )

    def render(self, gaussians: Gaussians, view: int):
        """Render training view `view` as the fit sees it (its background and backend)."""
        bg = torch.tensor(self.cfg.background, device=self.cfg.device)
        return render(gaussians, self.cams[view], background=bg, backend=self.cfg.backend)

    # --- schedule -----------------------------------------------------------------------------
    def fit(self, progress: bool = True, checkpoint: Path | None = None) -> dict:
        cfg = self.cfg
        rng = np.random.default_rng(cfg.seed + self.step)
        bar = tqdm(total=cfg.iterations, initial=self.step, desc="fit", disable=not progress)
        start = time.perf_counter() - self.elapsed
        recent_psnr = deque(maxlen=10)  # training-view PSNR of the last steps, for the bar
        while self.step < cfg.iterations:
            if cfg.time_budget_s is not None and time.perf_counter() - start > cfg.time_budget_s:
                self.stopped = "time_budget"
                break
            i = self.train_idx[int(rng.integers(len(self.train_idx)))]
            for group in self.optim.param_groups:
                if group["name"] == "means":
                    frac = self.step / max(cfg.iterations, 1)
                    group["lr"] = cfg.lr_means * self.extent * (0.01**frac)
            out = self.render(self.gaussians(), i)
            gt = self.images[i]
            l1 = (out.rgb - gt).abs().mean()
            loss = (1 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * (1 - ssim(out.rgb, gt))
            if cfg.lambda_aniso:
                loss = loss + cfg.lambda_aniso * self.anisotropy_penalty()
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            self._track_gradients(self.cams[i])
            self.optim.step()
            self.step += 1
            self.history.append(loss.item())
            recent_psnr.append(psnr(out.rgb.detach().clamp(0, 1), gt))
            if (
                cfg.densify_from <= self.step <= cfg.densify_until
                and self.step % cfg.densify_every == 0
            ):
                self.densify_and_prune()
            if (
                cfg.opacity_reset_every
                and self.step % cfg.opacity_reset_every == 0
                and self.step < cfg.densify_until
            ):
                self._reset_opacity()
            bar.update(1)
            if self.step % 10 == 0:
                bar.set_postfix(
                    loss=f"{np.mean(self.history[-10:]):.4f}",
                    psnr=f"{np.mean(recent_psnr):.2f}",
                    n=len(self),
                )
            if checkpoint is not None and self.step % cfg.checkpoint_every == 0:
                self.elapsed = time.perf_counter() - start
                self.save(checkpoint)
        bar.close()
        self.prune_near_cameras()
        self.elapsed = time.perf_counter() - start
        if checkpoint is not None:
            self.save(checkpoint)
        return self.evaluate()

    def anisotropy_penalty(self) -> torch.Tensor:
        """Mean excess of each Gaussian's axis ratio over `max_aspect` (0 when none exceeds
        it): keeps surfels from turning into needles that look right only edge-on."""
        log_s = self.params["log_scales"]
        log_ratio = log_s.max(dim=1).values - log_s.min(dim=1).values
        return F.relu(torch.exp(log_ratio) - self.cfg.max_aspect).mean()

    def _track_gradients(self, cam: Camera) -> None:
        grad = self.params["means"].grad
        if grad is None:
            return
        with torch.no_grad():
            depth = (self.params["means"] @ cam.rotation.T + cam.translation)[:, 2].clamp_min(1e-3)
            # a world-space move dx shifts the projection by f*dx/z pixels, so the loss gradient
            # per pixel is |grad| * z / f; the threshold is in those units times f
            g = grad.norm(dim=1) * depth
            seen = grad.abs().sum(1) > 0
            self.grad_accum[seen] += g[seen]
            self.grad_count[seen] += 1

    @torch.no_grad()
    def densify_and_prune(self) -> None:
        cfg = self.cfg
        avg = self.grad_accum / self.grad_count.clamp_min(1)
        big = avg > cfg.grad_threshold
        max_scale = torch.exp(self.params["log_scales"]).max(1).values
        clone = big & (max_scale <= cfg.percent_dense * self.extent)
        split = big & ~clone
        room = cfg.max_gaussians - len(self)
        grow = clone | split  # a split adds one Gaussian net, a clone one
        if int(grow.sum()) > max(room, 0):  # keep the strongest gradients that fit the cap
            allowed = torch.zeros_like(grow)
            if room > 0:
                allowed[torch.topk(torch.where(grow, avg, -1.0), room).indices] = True
            clone &= allowed
            split &= allowed
        p = {k: v.detach() for k, v in self.params.items()}
        new = {k: [v] for k, v in p.items()}
        if clone.any():
            for k, v in p.items():
                new[k].append(v[clone])
        keep = torch.ones(len(self), dtype=torch.bool, device=avg.device)
        if split.any():
            idx = torch.nonzero(split).squeeze(1)
            scales = torch.exp(p["log_scales"][idx])
            if scales.shape[1] == 2:
                scales = torch.cat([scales, torch.zeros_like(scales[:, :1])], 1)
            from sagonline.gaussians import quat_to_rotmat

            rot = quat_to_rotmat(F.normalize(p["quats"][idx], dim=1))
            # seeded by (seed, step): the same fit whatever else used torch's global generator,
            # and the same after a resume
            gen = torch.Generator(device=scales.device).manual_seed(
                self.cfg.seed * 1_000_003 + self.step
            )
            for _ in range(2):
                noise = torch.randn(scales.shape, generator=gen, device=scales.device)
                offset = (rot @ (noise * scales)[..., None])[..., 0]
                new["means"].append(p["means"][idx] + offset)
                new["log_scales"].append(p["log_scales"][idx] - math.log(1.6))
                for k in ("quats", "opacity_logit", "sh_dc", "sh_rest"):
                    new[k].append(p[k][idx])
            keep[idx] = False
        merged = {k: torch.cat(v) for k, v in new.items()}
        keep = torch.cat(
            [
                keep,
                torch.ones(len(merged["means"]) - len(keep), dtype=torch.bool, device=keep.device),
            ]
        )
        keep &= torch.sigmoid(merged["opacity_logit"]) >= cfg.prune_opacity
        keep &= self._clear_of_cameras(merged["means"])
        if cfg.opacity_reset_every and self.step > cfg.opacity_reset_every:
            # as 3DGS after its first opacity reset: Gaussians wider than a tenth of the scene
            keep &= torch.exp(merged["log_scales"]).max(1).values <= 0.1 * self.extent
        self.params = {k: v[keep].contiguous() for k, v in merged.items()}
        self._new_optimizer()

    def _clear_of_cameras(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: centres at least `camera_clearance` from every camera centre."""
        if not self.cfg.camera_clearance or self.cfg.camera_clearance <= 0:
            return torch.ones(len(means), dtype=torch.bool, device=means.device)
        nearest = torch.cdist(means, self.camera_centers.to(means.device)).min(dim=1).values
        return nearest >= self.cfg.camera_clearance

    @torch.no_grad()
    def prune_near_cameras(self) -> int:
        """Drop Gaussians inside the camera clearance; returns how many."""
        keep = self._clear_of_cameras(self.params["means"].detach())
        dropped = int((~keep).sum())
        if dropped:
            self.params = {k: v.detach()[keep].contiguous() for k, v in self.params.items()}
            self._new_optimizer()
        return dropped

    @torch.no_grad()
    def _reset_opacity(self) -> None:
        p = self.params["opacity_logit"]
        p.copy_(torch.minimum(p, torch.full_like(p, math.log(0.01 / 0.99))))

    @torch.no_grad()
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
            "fit_seconds": round(self.elapsed, 1),
            "heldout_views": [self.cams[i].name for i in self.held_idx],
            "final_loss": float(np.mean(self.history[-20:])) if self.history else None,
        }

    # --- checkpoints --------------------------------------------------------------------------
    def save(self, path: Path) -> None:
        state = {
            "params": {k: v.detach().cpu() for k, v in self.params.items()},
            "optim": self.optim.state_dict(),
            "step": self.step,
            "history": self.history,
            "elapsed": self.elapsed,
            "grad_accum": self.grad_accum.cpu(),
            "grad_count": self.grad_count.cpu(),
            "config": asdict(self.cfg),
        }
        atomic_write(path, lambda tmp: torch.save(state, tmp))

    def resume(self, path: Path) -> bool:
        """Continue an interrupted fit with the same settings; False if there is none."""
        if not path.is_file():
            return False
        state = torch.load(path, map_location="cpu", weights_only=False)
        if state["config"] != asdict(self.cfg):
            return False
        dev = self.cfg.device
        self.params = {k: v.to(dev) for k, v in state["params"].items()}
        self._new_optimizer()
        self.optim.load_state_dict(state["optim"])
        self.step, self.history, self.elapsed = state["step"], state["history"], state["elapsed"]
        self.grad_accum = state["grad_accum"].to(dev)
        self.grad_count = state["grad_count"].to(dev)
        return True


def write_fitted_scene(
    out_dir: Path, fitter: SceneFitter, all_cameras: list[Camera], metrics: dict
) -> Path:
    """point_cloud.ply + cameras.json (every camera of the scene) + fit_config.json +
    fit_metrics.json into `out_dir` (the dataset adapter's `gaussians/` folder)."""
    from sagonline.cameras import write_3dgs_cameras_json
    from sagonline.utils import atomic_write_json

    out_dir.mkdir(parents=True, exist_ok=True)
    write_ply(out_dir / "point_cloud.ply", fitter.export())
    write_3dgs_cameras_json(out_dir / "cameras.json", all_cameras)
    atomic_write_json(out_dir / "fit_config.json", asdict(fitter.cfg))
    atomic_write_json(out_dir / "fit_metrics.json", metrics)
    return out_dir / "point_cloud.ply"


__all__ = [
    "FitConfig",
    "SceneFitter",
    "psnr",
    "psnr_from_mse",
    "split_views",
    "ssim",
    "write_fitted_scene",
]
