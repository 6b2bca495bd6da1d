"""A monocular depth prior for the fit (`fit.lambda_depth`): each training photograph's depth as
a single-image network sees it, and the loss that asks the rendered depth to agree with it up
to scale and shift.

Where few photographs see a surface, nothing in the photometric loss fixes its depth: a surface
one photograph placed in front of the object matches that photograph as well as the right one,
and hides the object from between the photographs. A single-image depth network orders what a
photograph shows (the object before the wall, the table receding) without any second view. Its
depths carry no scale, so the loss compares shapes only: one minus the Pearson correlation of
the rendered and predicted depth, over the whole view and over patches of it (the sparse-view
splatting methods' depth-correlation loss: FSGS, Zhu et al. 2024; SparseGS, Xiong et al. 2023).

The network is an ONNX file run by onnxruntime (`make weights` fetches FastDepth, Wofk et al.
2019: a MobileNet trained on indoor scenes, 224 x 224 input, metric-like depth out)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sagonline.core.provenance import sha256_file
from sagonline.fitting.config import FitConfig
from sagonline.render.api import render
from sagonline.render.rasterize import RenderOutput
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

MAKE_TARGET = "make weights"


class DepthPriorError(ValueError):
    """The depth model cannot be used: names the setting and the file."""


class MonocularDepth:
    """An ONNX single-image depth network: one (H, W, 3) image in [0, 1] in, its (H, W) depth out
    (larger is farther). The model takes (1, 3, S, S) RGB in [0, 1] and gives (1, 1, S, S)."""

    def __init__(self, path: str | Path, option: str = "fit.depth_model"):
        self.path = Path(path)
        if not self.path.is_file():
            raise DepthPriorError(
                f"{option}={path}: no such file (run `{MAKE_TARGET}` to fetch FastDepth into "
                "weights/fastdepth/, or set the option to an ONNX depth model)"
            )
        try:
            import onnxruntime as ort
        except ImportError:
            raise DepthPriorError(
                f"{option}={path}: onnxruntime is not installed (`make install-extras`)"
            ) from None
        options = ort.SessionOptions()
        options.log_severity_level = 3  # the exporter's unused initialisers, one line each
        try:
            self.session = ort.InferenceSession(
                str(self.path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime raises its own classes for a damaged file
            raise DepthPriorError(
                f"{option}={path}: not a model onnxruntime can run ({exc})"
            ) from None
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        shape = inputs[0].shape
        fixed = len(shape) == 4 and all(isinstance(n, int) for n in shape[2:])
        if len(inputs) != 1 or len(outputs) != 1 or not fixed or shape[1] != 3:
            raise DepthPriorError(
                f"{option}={path}: it takes {[i.shape for i in inputs]} and gives "
                f"{len(outputs)} outputs; a depth model takes one (1, 3, H, W) RGB image of a "
                "fixed size and gives one depth map"
            )
        self.input_name, self.size = inputs[0].name, (int(shape[2]), int(shape[3]))
        self.sha256 = sha256_file(self.path)

    def __call__(
        self,
        image: torch.Tensor,  # [H, W, 3] in [0, 1]
    ) -> torch.Tensor:  # [H, W] depth, larger is farther
        """The network's depth of one image, resized back to the image's (H, W)."""
        H, W = image.shape[:2]
        x = image.detach().float().cpu().permute(2, 0, 1)[None]
        x = F.interpolate(x, size=self.size, mode="area")
        (depth,) = self.session.run(None, {self.input_name: x.numpy().astype(np.float32)})
        depth = torch.from_numpy(np.asarray(depth, dtype=np.float32)).reshape(1, 1, *self.size)
        depth = F.interpolate(depth, size=(H, W), mode="bilinear", align_corners=False)[0, 0]
        if not bool(torch.isfinite(depth).all()):
            raise DepthPriorError(f"{self.path}: the depth model gave NaN or Inf")
        return depth.to(image.device)


def pearson(
    a: torch.Tensor,  # [..., P] samples in the last dimension
    b: torch.Tensor,  # [..., P]
    weights: torch.Tensor,  # [..., P] 1 where a sample counts, else 0
) -> torch.Tensor:  # [...] correlation in [-1, 1]; 0 where a side has no spread
    """Weighted Pearson correlation along the last dimension."""
    n = weights.sum(-1, keepdim=True).clamp_min(1)
    da = (a - (a * weights).sum(-1, keepdim=True) / n) * weights
    db = (b - (b * weights).sum(-1, keepdim=True) / n) * weights
    cov = (da * db).sum(-1)
    return cov / ((da * da).sum(-1) * (db * db).sum(-1)).clamp_min(1e-20).sqrt()


def depth_correlation(
    depth: torch.Tensor,  # [H, W] alpha-weighted rendered depth
    alpha: torch.Tensor,  # [H, W]
    prior: torch.Tensor,  # [H, W] the network's depth of the photograph
    patch: int = 32,
    min_alpha: float = 0.5,
    trust: bool = False,
    pool: int = 1,
) -> torch.Tensor:  # [] in [0, 2]
    """The depth prior's loss: the mean of (1 - Pearson correlation) of the rendered surface depth
    (depth / alpha) with the prior over the view's pixels where alpha > `min_alpha`, and the
    same averaged over the view's `patch` x `patch` tiles that have at least a quarter of their
    pixels covered (the whole view orders near and far; the tiles, each surface against what
    surrounds it; `patch` 0: the whole view only). 0 when the two agree up to a positive scale
    and a shift; no gradient through alpha. 0 (with a gradient of zeros) where nothing is
    covered. `trust`: each term (the view's, each tile's) is weighted by the correlation it
    already has, clamped at 0 and taken without gradient, so the network is followed where it
    orders the surfaces as the fit roughly does and ignored where it contradicts them (a
    network that misreads a view, say a white backdrop, cannot pull the fit against its
    photographs). `pool` > 1: both depths are first averaged over `pool` x `pool` blocks of
    covered pixels (a block counts when most of it is covered; `patch` is then in blocks' units
    times `pool`), so the render is compared at the detail the network resolves: a 224-pixel
    network blurs a silhouette, and pixel by pixel the term would pull the object's edges toward
    the blur."""
    covered = (alpha.detach() > min_alpha).to(depth.dtype)
    if not bool(covered.any()):
        return depth.sum() * 0
    surface = depth / alpha.detach().clamp_min(1e-6)
    if pool > 1 and min(surface.shape) >= pool:
        surface, prior, covered = pooled(surface, prior, covered, pool)
        patch //= pool
    whole = trusted(1 - pearson(surface.flatten(), prior.flatten(), covered.flatten()), trust)
    H, W = surface.shape
    if patch == 0 or patch > min(H, W):  # the whole view only
        return whole

    def tiles(t: torch.Tensor) -> torch.Tensor:  # [H, W] -> [tiles, patch * patch]
        return blocks(t, patch).flatten(0, 1)

    w = tiles(covered)
    used = w.sum(-1) >= patch * patch / 4
    if not bool(used.any()):
        return whole
    local = trusted(1 - pearson(tiles(surface)[used], tiles(prior)[used], w[used]), trust)
    return 0.5 * (whole + local.mean())


def pooled(
    surface: torch.Tensor,  # [H, W] rendered surface depth
    prior: torch.Tensor,  # [H, W]
    covered: torch.Tensor,  # [H, W] 1 where covered, else 0
    pool: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # each [H // pool, W // pool]
    """`depth_correlation`'s `pool` (a view at least `pool` pixels a side): the covered pixels'
    mean of each depth per block, and 1 where more than half of the block is covered."""
    share = blocks(covered, pool).sum(-1)
    count = share.clamp_min(1)
    mean_surface = blocks(surface * covered, pool).sum(-1) / count
    mean_prior = blocks(prior * covered, pool).sum(-1) / count
    return mean_surface, mean_prior, (share > pool * pool / 2).to(surface.dtype)


def blocks(
    t: torch.Tensor,  # [H, W]
    size: int,
) -> torch.Tensor:  # [H // size, W // size, size * size]
    """The whole `size` x `size` blocks of `t` (a remainder at the right and bottom is left
    out), each block's pixels in the last dimension."""
    rows, cols = t.shape[0] // size, t.shape[1] // size
    t = t[: rows * size, : cols * size].reshape(rows, size, cols, size)
    return t.permute(0, 2, 1, 3).reshape(rows, cols, size * size)


def trusted(
    term: torch.Tensor,  # [...] 1 - correlation, in [0, 2]
    trust: bool,
) -> torch.Tensor:  # [...] the term, times its own correlation (clamped at 0, no gradient)
    """`depth_correlation`'s `trust` weighting: unchanged without it."""
    return term * (1 - term.detach()).clamp_min(0) if trust else term


def between(
    a: Camera,
    b: Camera,
    t: float,
) -> Camera:
    """A camera a fraction `t` of the way from `a` to `b`: the centre on the line between
    theirs, the rotation slerped, `a`'s intrinsics and size (a view between two photographs,
    where nothing photographed checks what the fit draws)."""
    from scipy.spatial.transform import Rotation, Slerp

    rotations = Rotation.from_matrix(
        np.stack(
            [a.rotation.detach().cpu().double().numpy(), b.rotation.detach().cpu().double().numpy()]
        )
    )
    R = torch.from_numpy(Slerp([0.0, 1.0], rotations)(t).as_matrix()).to(a.world_to_cam)
    centre = (1 - t) * a.center + t * b.center
    pose = torch.eye(4, dtype=a.world_to_cam.dtype, device=a.world_to_cam.device)
    pose[:3, :3], pose[:3, 3] = R, -R @ centre
    return replace(a, world_to_cam=pose, name=f"{a.name}~{b.name}@{t:.2f}")


def pseudo_view_term(
    fitter,
    gaussians: Gaussians,
) -> torch.Tensor | None:  # [] or None on the steps without one
    """The depth prior in a view between two neighbouring training photographs, on every
    `fit.depth_pseudo_every`-th step from `fit.depth_pseudo_from`: the network's depth of the
    fit's own render there (no gradient), which the render's depth must follow (the pseudo views
    of FSGS, Zhu et al. 2024). A surface one photograph placed in front of the object shows
    there as a blob the network puts where what surrounds it lies. The view is drawn from
    (seed, step): a resumed fit draws the same."""
    cfg, step = fitter.cfg, fitter.step
    if not (cfg.lambda_depth > 0 and cfg.depth_pseudo_every > 0) or step < cfg.depth_pseudo_from:
        return None
    if step % cfg.depth_pseudo_every:
        return None
    rng = np.random.default_rng([cfg.seed, step])
    a = fitter.train_idx[int(rng.integers(len(fitter.train_idx)))]
    b = fitter.neighbours[a][int(rng.integers(len(fitter.neighbours[a])))]
    cam = between(fitter.cams[a], fitter.cams[b], float(rng.uniform(0.25, 0.75)))
    background = torch.tensor(cfg.background, device=cam.K.device)
    out = render(gaussians, cam, background=background, backend=cfg.backend)
    prior = fitter.depth_model(out.rgb.detach().clamp(0, 1))
    return prior_term(cfg, out, prior)


def prior_term(
    cfg: FitConfig,
    out: RenderOutput,
    prior: torch.Tensor,  # [H, W] the network's depth of the view
) -> torch.Tensor:  # []
    """`depth_correlation` of a render (`out`: its (H, W) depth and alpha) at the fit's settings
    (`fit.depth_patch`, `fit.depth_trust`, `fit.depth_pool`)."""
    return depth_correlation(
        out.depth, out.alpha, prior, cfg.depth_patch, trust=cfg.depth_trust, pool=cfg.depth_pool
    )
