"""Fit a Gaussian scene (2DGS by default, 3DGS as an option) to posed images.

config        FitConfig: the recipe's settings (Hydra schema `fit/schema`)
capture       images at the fitting size, start points and near depth from a capture on disk
start_points  training/held-out split, random points in the frusta
losses        L1 + D-SSIM, PSNR, the needle penalty, the geometric regularisers
depth_prior   the optional monocular depth prior: an ONNX depth network, its correlation loss
strategy      densify / prune / opacity reset, hooks around the optimiser step
trainer       SceneFitter (the loop, evaluation, checkpoints)
threads       torch's own ops on one thread, the compiled kernel on all (same scene on any count)
finish        the carve and polish after the last iteration, write_fitted_scene
"""

from sagonline.fitting.config import FitConfig
from sagonline.fitting.finish import write_fitted_scene
from sagonline.fitting.losses import psnr, psnr_from_mse, ssim
from sagonline.fitting.start_points import split_views
from sagonline.fitting.strategy import DensifyStrategy
from sagonline.fitting.trainer import SceneFitter

__all__ = [
    "DensifyStrategy",
    "FitConfig",
    "SceneFitter",
    "psnr",
    "psnr_from_mse",
    "split_views",
    "ssim",
    "write_fitted_scene",
]
