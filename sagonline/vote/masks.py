"""One frame's mask checked against its view before it votes: its size, its values and its
label range (`MaskError` names the frame and what is wrong)."""

from __future__ import annotations

import numpy as np
import torch

from sagonline.core.tensors import tensor_view
from sagonline.scene.cameras import Camera


class MaskError(ValueError):
    """A 2D mask does not fit its view (size, dtype or label range)."""


def check_mask(
    mask: np.ndarray | torch.Tensor,  # [H, W] label ids
    camera: Camera,
    num_labels: int,
    where: str,
) -> torch.Tensor:  # [H * W] long
    """Validate one frame's mask against its view; returns (H*W,) long."""
    m = tensor_view(np.asarray(mask) if not isinstance(mask, torch.Tensor) else mask)
    if m.shape != (camera.height, camera.width):
        raise MaskError(
            f"{where}: mask is {tuple(m.shape)} but its view '{camera.name}' renders "
            f"at {camera.height}x{camera.width} (H x W)"
        )
    if m.dtype.is_floating_point or m.dtype == torch.bool:
        if m.dtype == torch.bool:
            m = m.long()
        elif not torch.equal(m, m.round()):
            raise MaskError(f"{where}: mask holds non-integer values; pass label ids")
    m = m.long()
    lo, hi = int(m.min()), int(m.max())
    if lo < 0 or hi >= num_labels:
        raise MaskError(f"{where}: label ids must lie in [0, {num_labels}), found [{lo}, {hi}]")
    return m.flatten()


__all__ = ["MaskError", "check_mask"]
