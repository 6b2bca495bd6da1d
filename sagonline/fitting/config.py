"""The fitting recipe's settings, one default each (registered as the Hydra schema `fit/schema`;
conf/scenes.yaml only overrides)."""

from __future__ import annotations

from dataclasses import dataclass

from sagonline.settings import check_settings


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
    # 2DGS's geometric regularisers (`losses.depth_distortion`, `losses.normal_consistency`),
    # each from its own iteration on (2DGS: 3000 and 7000 of 30000); 0: off. Chosen on mold_cape
    # (README, "Fitting on CPU"): real masks voting, 85.2 -> 89.5 / 91.1 mIoU on two seeds;
    # lambda_dist=1 gave 88.3, 100 collapsed the fit (55.9)
    lambda_dist: float = 10.0
    dist_from: int = 300
    lambda_normal: float = 0.05
    normal_from: int = 700
    lr_means: float = 1.6e-4  # times the scene extent, decayed to 1% by the end
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh: float = 2.5e-3  # degree 0; higher degrees learn 20x slower (as 3DGS)
    # prune Gaussians this close to any camera centre; 0: off; None: the caller's automatic
    # value (`make scenes`: half the nearest recorded depth), off when none is given
    camera_clearance: float | None = None
    # prune Gaussians whose 3-sigma footprint reaches into a view nearer than this fraction of
    # the nearest depth recorded for that view (LLFF bounds, else the start points' depths in
    # it); 0: off. The floaters that hide the object in views between the photographs sit there.
    # Chosen on mold_cape (README, "Fitting on CPU"): real masks voting 89.5 / 91.1 -> 94.8 / 94.6
    view_clearance: float = 0.85
    view_clearance_views: str = "train"  # train: the training photographs' depths; all: every pose
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
    backend: str = "auto"  # auto: gsplat on CUDA, the compiled kernel on the CPU, else PyTorch

    def __post_init__(self) -> None:
        self.background = tuple(self.background)  # Hydra hands lists in
        budget = self.time_budget_s
        check_settings(
            "fit",
            kind=(self.kind in ("2dgs", "3dgs"), self.kind, "2dgs or 3dgs"),
            iterations=(self.iterations >= 1, self.iterations, ">= 1"),
            max_side=(self.max_side >= 8, self.max_side, ">= 8 pixels"),
            sh_degree=(0 <= self.sh_degree <= 3, self.sh_degree, "0, 1, 2 or 3"),
            max_gaussians=(self.max_gaussians >= 1, self.max_gaussians, ">= 1"),
            time_budget_s=(budget is None or budget >= 0, budget, ">= 0 seconds, or null"),
            view_clearance=(self.view_clearance >= 0, self.view_clearance, ">= 0"),
            lambda_dist=(self.lambda_dist >= 0, self.lambda_dist, ">= 0"),
            lambda_normal=(self.lambda_normal >= 0, self.lambda_normal, ">= 0"),
            lambda_dssim=(0 <= self.lambda_dssim <= 1, self.lambda_dssim, "in [0, 1]"),
        )
