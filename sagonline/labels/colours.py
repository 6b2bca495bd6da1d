"""The labels' colours, one per label id wherever labels are drawn: masks, recordings, the
viewer, exported renders and figures."""

from __future__ import annotations

import numpy as np

BACKGROUND_3D = (190, 180, 160)  # Gaussians labelled background, in the 3D view

PALETTE = np.array(
    [
        [0, 0, 0],
        [230, 25, 75],
        [60, 180, 75],
        [255, 225, 25],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [210, 245, 60],
        [250, 190, 212],
        [0, 128, 128],
        [220, 190, 255],
        [170, 110, 40],
        [255, 250, 200],
        [128, 0, 0],
    ],
    dtype=np.uint8,
)


def label_colors(num_labels: int) -> np.ndarray:
    """(num_labels, 3) uint8: label k's colour, the palette repeated where it runs out (0 is
    black, the background in masks)."""
    reps = int(np.ceil(num_labels / len(PALETTE)))
    return np.tile(PALETTE, (reps, 1))[:num_labels]
