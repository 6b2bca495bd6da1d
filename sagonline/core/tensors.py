"""NumPy arrays as tensors without a copy, the read-only ones included."""

from __future__ import annotations

import warnings

import numpy as np
import torch


def tensor_view(
    array: np.ndarray | torch.Tensor,  # [...] any shape
) -> torch.Tensor:  # [...] the same shape, sharing the array's memory
    """`torch.as_tensor(array)`, sharing its memory. The ground truth is read-only
    (`datasets.base.read_only`) and is only read through the tensor, so PyTorch's warning
    that it cannot mark a tensor read-only is not shown for it."""
    if isinstance(array, np.ndarray) and not array.flags.writeable:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
            return torch.as_tensor(array)
    return torch.as_tensor(array)
