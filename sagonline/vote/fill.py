"""After the vote (`consensus.fill`, off by default): unlabelled Gaussians take the label of
their labelled neighbours in 3D, where those agree."""

from __future__ import annotations

import numpy as np
import torch


def fill_from_neighbours(
    means: torch.Tensor,  # [N, 3]
    labels: torch.Tensor,  # [N] int64, -1 unlabelled
    k: int,
) -> tuple[torch.Tensor, torch.Tensor]:  # [N] labels, [N] bool filled
    """Each unlabelled Gaussian takes the label a strict majority of its k nearest labelled
    neighbours share, counting only neighbours within 4x the labelled Gaussians' median
    nearest-neighbour spacing (a Gaussian far from every labelled one, a floater, stays
    unlabelled). The vote's own labels are never changed."""
    from scipy.spatial import cKDTree

    labelled = labels >= 0
    known = labelled.cpu().numpy()
    unknown = ~known
    out = labels.clone()
    filled = torch.zeros_like(labelled)
    if known.sum() < 2 or not unknown.any():
        return out, filled
    pts = means.detach().float().cpu().numpy()
    tree = cKDTree(pts[known])
    spacing = float(np.median(tree.query(pts[known], k=2)[0][:, 1]))
    k = min(k, int(known.sum()))
    dist, idx = tree.query(pts[unknown], k=k, distance_upper_bound=4 * spacing)
    dist, idx = dist.reshape(len(idx), -1), idx.reshape(len(idx), -1)
    near = np.isfinite(dist)
    known_labels = labels.cpu().numpy()[known]
    neighbour = np.where(near, known_labels[np.minimum(idx, len(known_labels) - 1)], -1)
    best = np.full(len(idx), -1, np.int64)
    for label in np.unique(known_labels):
        count = (neighbour == label).sum(1)
        best = np.where(count * 2 > k, label, best)
    rows = np.flatnonzero(unknown)[best >= 0]
    rows_t = torch.from_numpy(rows).to(labels.device)
    out[rows_t] = torch.from_numpy(best[best >= 0]).to(labels.device, labels.dtype)
    filled[rows_t] = True
    return out, filled
