"""The built-in datasets, registered in `plugins.DATASETS`: each key with its typed config
(`configs.py`) and the adapter that config builds. A dataset of one's own registers the same
way (docs/extending.md)."""

from __future__ import annotations

from dataclasses import asdict

from sagonline.core.plugins import DATASETS, settings_dict
from sagonline.datasets.configs import (
    CaptureConfig,
    Desktop360Config,
    KITTI360Config,
    LERFMaskConfig,
    Mip360Config,
    NeRDS360Config,
    NVOSConfig,
    PosedMasksConfig,
    SPInNeRFConfig,
    SyntheticConfig,
    UDDConfig,
)
from sagonline.datasets.generic import PosedMasksDataset
from sagonline.datasets.nvos import NVOSDataset
from sagonline.datasets.spinnerf import SPInNeRFDataset
from sagonline.datasets.synthetic import SyntheticDataset


def _posed_masks(cfg: PosedMasksConfig):
    """A capture with poses and per-view label maps."""
    return PosedMasksDataset(**settings_dict(cfg))


def _nvos(cfg: NVOSConfig):
    """NVOS: 8 tasks, the target view of each scored."""
    return NVOSDataset(**settings_dict(cfg))


def _spinnerf(cfg: SPInNeRFConfig):
    """SPIn-NeRF: 10 scenes, every masked view scored."""
    return SPInNeRFDataset(**settings_dict(cfg))


def _synthetic(cfg: SyntheticConfig):
    """Generated 2DGS scenes with per-Gaussian ground truth (the embedded default)."""
    presets = {k: asdict(p) for k, p in cfg.presets().items()}
    return SyntheticDataset(presets, cfg.scenes, device=cfg.device)


for _key, _config, _build in (
    ("generic", PosedMasksConfig, _posed_masks),
    ("capture", CaptureConfig, _posed_masks),
    ("kitti360", KITTI360Config, _posed_masks),
    ("udd", UDDConfig, _posed_masks),
    ("mip360", Mip360Config, _posed_masks),
    ("lerf_mask", LERFMaskConfig, _posed_masks),
    ("desktop360", Desktop360Config, _posed_masks),
    ("nerds360", NeRDS360Config, _posed_masks),
    ("spinnerf", SPInNeRFConfig, _spinnerf),
    ("nvos", NVOSConfig, _nvos),
    ("synthetic", SyntheticConfig, _synthetic),
):
    DATASETS.register(_key, _config, _build, summary=(_config.__doc__ or "").split("\n")[0])
