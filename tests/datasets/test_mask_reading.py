"""Masks as a dataset reads them: 0/1 masks read as binary are refused."""

from __future__ import annotations

import numpy as np
import pytest

from sagonline.datasets.base import DatasetError
from tests.fixtures import (
    write_image,
)


def test_zero_one_masks_read_as_binary_are_refused(tmp_path):
    from sagonline.datasets.common import load_mask

    path = tmp_path / "m.png"
    write_image(path, (np.arange(48).reshape(6, 8) % 2).astype(np.uint8))
    with pytest.raises(DatasetError, match=r"m\.png.*mask_threshold=0"):
        load_mask(path, threshold=127)
    assert load_mask(path, threshold=0).sum() == 24
