"""Stage II: the dual-branch refinement student, distilled online from the 2D masks."""

from sagonline.refine.network import DualBranchRefiner, ResNetEncoder, load_imagenet_weights
from sagonline.refine.trainer import RefineConfig, RefinementTrainer

__all__ = [
    "DualBranchRefiner",
    "RefineConfig",
    "RefinementTrainer",
    "ResNetEncoder",
    "load_imagenet_weights",
]
