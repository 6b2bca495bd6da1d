"""Densification and pruning (the 3DGS schedule) as a strategy with hooks around the optimiser
step, the way gsplat splits it: the trainer calls `after_backward` to collect positional
gradients and `after_step`, which may return a new parameter set (the trainer then rebuilds its
optimiser). Every `densify_every` iterations between `densify_from` and `densify_until`,
Gaussians whose accumulated positional gradient exceeds `grad_threshold` are cloned (small) or
split in two (large), and nearly transparent ones (opacity < `prune_opacity`) are pruned (after
the first opacity reset also those wider than a tenth of the scene); opacities are reset every
`opacity_reset_every` iterations. Gaussians closer than `camera_clearance` to any camera of the
capture are pruned at every densification step (and, by the trainer, at the start and end), and
with `view_clearance` those reaching into a posed view nearer than that fraction of the view's
recorded near depth."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from sagonline.fitting.config import FitConfig
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import quat_to_rotmat

Params = dict[str, torch.Tensor]  # raw parameters: means, log_scales, quats, opacity_logit, sh_*


class DensifyStrategy:
    """Gradient statistics and the densify / prune / opacity-reset rules of one fit.
    camera_centers: (C, 3) every camera of the capture; extent: the scene's radius; views and
    view_near: the posed views and the nearest depth recorded for each (0: unknown), for
    `view_clearance`; pose_views: (camera, near depth) of the views without a photograph, for
    `pose_view_clearance`."""

    def __init__(
        self,
        cfg: FitConfig,
        camera_centers: torch.Tensor,
        extent: float,
        views: list[Camera] = (),
        view_near: list[float] = (),
        pose_views: list[tuple[Camera, float]] = (),
    ):
        pairs = zip(views, view_near, strict=True)  # one near depth per view
        self.views = [(c.to(cfg.device), float(d)) for c, d in pairs if d > 0]
        self.pose_views = [(c.to(cfg.device), float(d)) for c, d in pose_views if d > 0]
        self.cfg, self.extent = cfg, extent
        self.camera_centers = camera_centers.to(cfg.device, torch.float32)
        self.reset(0)

    def reset(self, n: int) -> None:
        """Fresh gradient statistics for `n` Gaussians (after the parameter set changed)."""
        self.grad_accum = torch.zeros(n, device=self.cfg.device)
        self.grad_count = torch.zeros(n, device=self.cfg.device)

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum.cpu(), "grad_count": self.grad_count.cpu()}

    def load_state_dict(self, state: dict) -> None:
        self.grad_accum = state["grad_accum"].to(self.cfg.device)
        self.grad_count = state["grad_count"].to(self.cfg.device)

    def clear_of_cameras(
        self,
        means: torch.Tensor,  # [N, 3]
        log_scales: torch.Tensor | None = None,  # [N, 2] or [N, 3]
    ) -> torch.Tensor:  # [N] bool
        """(N,) bool: centres at least `camera_clearance` from every camera centre and, with
        `view_clearance`, footprints (3 sigma of the largest scale; the centre alone without
        log_scales) clear of every view's image nearer than view_clearance x its near depth."""
        keep = torch.ones(len(means), dtype=torch.bool, device=means.device)
        if self.cfg.camera_clearance and self.cfg.camera_clearance > 0:
            nearest = torch.cdist(means, self.camera_centers.to(means.device)).min(dim=1).values
            keep &= nearest >= self.cfg.camera_clearance
        if self.cfg.view_clearance > 0:
            radius = (
                torch.zeros(len(means), device=means.device)
                if log_scales is None
                else 3.0 * torch.exp(log_scales).max(dim=1).values
            )
            for cam, near in self.views:
                keep &= ~in_front_of_view(means, radius, cam, self.cfg.view_clearance * near)
        return keep

    # --- hooks around the optimiser step ------------------------------------------------------
    @torch.no_grad()
    def after_backward(self, params: Params, cam: Camera) -> None:
        """Accumulate each Gaussian's positional gradient in pixel units (world-space gradient
        times depth; the threshold is in those units times the focal length)."""
        grad = params["means"].grad
        if grad is None:
            return
        depth = (params["means"] @ cam.rotation.T + cam.translation)[:, 2].clamp_min(1e-3)
        g = grad.norm(dim=1) * depth
        seen = grad.abs().sum(1) > 0  # added by arithmetic, not by a boolean index: no wait on
        self.grad_accum += torch.where(seen, g, 0.0)  # the GPU for the count of those seen
        self.grad_count += seen

    @torch.no_grad()
    def after_step(self, params: Params, step: int) -> Params | None:
        """Densify/prune and reset opacities when the schedule says so (`step` counts the
        optimiser steps done). Returns the new parameter set when it changed, else None."""
        cfg = self.cfg
        new = None
        if cfg.densify_from <= step <= cfg.densify_until and step % cfg.densify_every == 0:
            new = self.densify_and_prune(params, step)
            params = new
        if (
            cfg.opacity_reset_every
            and step % cfg.opacity_reset_every == 0
            and step < cfg.densify_until
        ):
            p = params["opacity_logit"]
            p.copy_(torch.minimum(p, torch.full_like(p, math.log(0.01 / 0.99))))
        if cfg.opacity_decay < 1 and step <= cfg.densify_until:
            p = params["opacity_logit"]
            p.copy_(torch.logit(torch.sigmoid(p) * cfg.opacity_decay))
        return new

    @torch.no_grad()
    def densify_and_prune(self, params: Params, step: int) -> Params:
        cfg = self.cfg
        n = len(params["means"])
        avg = self.grad_accum / self.grad_count.clamp_min(1)
        big = avg > cfg.grad_threshold
        max_scale = torch.exp(params["log_scales"]).max(1).values
        clone = big & (max_scale <= cfg.percent_dense * self.extent)
        split = big & ~clone
        room = cfg.max_gaussians - n
        grow = clone | split  # a split adds one Gaussian net, a clone one
        if int(grow.sum()) > max(room, 0):  # keep the strongest gradients that fit the cap
            allowed = torch.zeros_like(grow)
            if room > 0:
                allowed[torch.topk(torch.where(grow, avg, -1.0), room).indices] = True
            clone &= allowed
            split &= allowed
        p = {k: v.detach() for k, v in params.items()}
        new = {k: [v] for k, v in p.items()}
        if clone.any():
            for k, v in p.items():
                new[k].append(v[clone])
        keep = torch.ones(n, dtype=torch.bool, device=avg.device)
        if split.any():
            idx = torch.nonzero(split).squeeze(1)
            scales = torch.exp(p["log_scales"][idx])
            if scales.shape[1] == 2:
                scales = torch.cat([scales, torch.zeros_like(scales[:, :1])], 1)
            rot = quat_to_rotmat(F.normalize(p["quats"][idx], dim=1))
            # seeded by (seed, step): the same fit whatever else used torch's global generator,
            # and the same after a resume
            gen = torch.Generator(device=scales.device).manual_seed(cfg.seed * 1_000_003 + step)
            for _ in range(2):
                noise = torch.randn(scales.shape, generator=gen, device=scales.device)
                offset = (rot @ (noise * scales)[..., None])[..., 0]
                new["means"].append(p["means"][idx] + offset)
                new["log_scales"].append(p["log_scales"][idx] - math.log(1.6))
                for k in ("quats", "opacity_logit", "sh_dc", "sh_rest"):
                    new[k].append(p[k][idx])
            keep[idx] = False
        merged = {k: torch.cat(v) for k, v in new.items()}
        grown = len(merged["means"]) - n
        keep = torch.cat([keep, torch.ones(grown, dtype=torch.bool, device=keep.device)])
        keep &= torch.sigmoid(merged["opacity_logit"]) >= cfg.prune_opacity
        keep &= self.clear_of_cameras(merged["means"], merged["log_scales"])
        if cfg.opacity_reset_every and step > cfg.opacity_reset_every:
            # as 3DGS after its first opacity reset: Gaussians wider than a tenth of the scene
            keep &= torch.exp(merged["log_scales"]).max(1).values <= 0.1 * self.extent
        return {k: v[keep].contiguous() for k, v in merged.items()}

    @torch.no_grad()
    def prune_near_cameras(self, params: Params) -> tuple[Params | None, int]:
        """Drop Gaussians inside the camera clearance: (new parameters or None, how many)."""
        keep = self.clear_of_cameras(params["means"].detach(), params["log_scales"].detach())
        return keep_only(params, keep)

    @torch.no_grad()
    def prune_pose_views(self, params: Params) -> tuple[Params | None, int]:
        """After the fit: drop Gaussians reaching into a pose-only view (`clear_of_pose_views`)."""
        keep = clear_of_pose_views(
            params["means"].detach(),
            params["log_scales"].detach(),
            self.pose_views,
            self.cfg.pose_view_clearance,
        )
        return keep_only(params, keep)


def keep_only(
    params: Params,
    keep: torch.Tensor,  # [N] bool
) -> tuple[Params | None, int]:
    """The parameters of the kept Gaussians and how many went (None, 0 when none went)."""
    dropped = int((~keep).sum())
    if not dropped:
        return None, 0
    return {k: v.detach()[keep].contiguous() for k, v in params.items()}, dropped


def clear_of_pose_views(
    means: torch.Tensor,  # [N, 3]
    log_scales: torch.Tensor,  # [N, 2] or [N, 3]
    pose_views: list[tuple[Camera, float]],  # (camera, near depth) of the pose-only views
    fraction: float,
) -> torch.Tensor:  # [N] bool
    """(N,) bool: footprints (3 sigma of the largest scale) clear of every pose-only view's
    image nearer than fraction x its near depth (`FitConfig.pose_view_clearance`)."""
    keep = torch.ones(len(means), dtype=torch.bool, device=means.device)
    if fraction <= 0:
        return keep
    radius = 3.0 * torch.exp(log_scales).max(dim=1).values
    for cam, near in pose_views:
        keep &= ~in_front_of_view(means, radius, cam, fraction * near)
    return keep


def in_front_of_view(
    means: torch.Tensor,  # [N, 3]
    radius: torch.Tensor,  # [N] world units
    cam: Camera,
    depth: float,
) -> torch.Tensor:  # [N] bool
    """(N,) bool: centres in front of `cam` nearer than `depth` whose disc of `radius` (N,)
    (world units, drawn at the centre's depth) overlaps its image."""
    uv, z = cam.to(means.device).project(means)
    close = (z > 0) & (z < depth)
    r = radius * cam.K[:2, :2].diagonal().max().to(means) / z.clamp_min(1e-9)
    u, v = uv[:, 0], uv[:, 1]
    overlaps = (u + r > 0) & (u - r < cam.width) & (v + r > 0) & (v - r < cam.height)
    return close & overlaps


def looked_through(
    means: torch.Tensor,  # [N, 3]
    cam: Camera,
    alpha: torch.Tensor,  # [H, W] the view's rendered opacity
    depth: torch.Tensor,  # [H, W] its alpha-weighted depth
    margin: float,
) -> torch.Tensor:  # [N] bool
    """(N,) bool: centres inside `cam`'s image, nearer by more than `margin` (a fraction) than
    the opaque surface (alpha > 0.5) rendered at their pixel: the photograph sees past them
    (`FitConfig.carve_views`)."""
    uv, z = cam.to(means.device).project(means)
    u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    u, v = u.clamp(0, cam.width - 1), v.clamp(0, cam.height - 1)
    a = alpha[v, u]
    surface = depth[v, u] / a.clamp_min(1e-6)
    return inside & (a > 0.5) & (z < (1 - margin) * surface)
