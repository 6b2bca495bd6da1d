"""After the vote (`consensus.body`, off by default): each object's labels kept on its body,
the largest cluster of its Gaussians, so that floaters which voted for the object in the
voting views but float apart from it are left unlabelled. The diagnosis uses the same `Body`
to say which Gaussians outside the silhouette float (`score.diagnosis`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

LINK = 3.0  # Gaussians closer than LINK x the median nearest-neighbour spacing are linked


@dataclass
class Body:
    """An object's body: the largest cluster of its Gaussians linked by gaps under LINK x
    their median nearest-neighbour spacing (floaters labelled as the object fall outside it)."""

    members: np.ndarray  # [N] bool, the Gaussians of the body
    radius: float  # the median distance of its Gaussians from their median

    @classmethod
    def of(cls, means: np.ndarray, members: np.ndarray) -> Body:  # means [N, 3], members [N]
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        index = np.flatnonzero(members)
        body = np.zeros(len(means), bool)
        if index.size < 2:
            body[index] = True
            return cls(body, 1.0)
        points = means[index]
        tree = cKDTree(points)
        spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
        pairs = tree.query_pairs(LINK * spacing, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), (len(index),) * 2)
        _, component = connected_components(graph, directed=False)
        body[index[component == np.bincount(component).argmax()]] = True
        centre = np.median(means[body], 0)
        radius = float(np.median(np.linalg.norm(means[body] - centre, axis=1))) or 1.0
        return cls(body, radius)

    def distance(self, means: np.ndarray, ids: np.ndarray) -> np.ndarray:  # [M] ids -> [M]
        """Each Gaussian's distance to the body's nearest Gaussian in body radii (0 in it)."""
        from scipy.spatial import cKDTree

        gap = cKDTree(means[self.members]).query(means[ids])[0] / self.radius
        return np.where(self.members[ids], 0.0, gap)


def keep_bodies(
    means: torch.Tensor,  # [N, 3]
    labels: torch.Tensor,  # [N] int64, -1 unlabelled
) -> tuple[torch.Tensor, torch.Tensor]:  # [N] labels, [N] bool dropped
    """Each object label (>= 1) kept on its body only; its Gaussians outside the body become
    unlabelled. Background (0) and unlabelled Gaussians are left as they are."""
    out, dropped = labels.clone(), torch.zeros_like(labels, dtype=torch.bool)
    points = means.detach().float().cpu().numpy()
    known = labels.cpu().numpy()
    for k in np.unique(known[known > 0]).tolist():
        members = known == k
        off = members & ~Body.of(points, members).members
        if off.any():
            rows = torch.from_numpy(np.flatnonzero(off)).to(labels.device)
            out[rows] = -1
            dropped[rows] = True
    return out, dropped
