"""After the vote (`consensus.body`, off by default): each object's labels kept on its body,
the largest cluster of its touching Gaussians, so that floaters which voted for the object in
the voting views but touch nothing of it are left unlabelled. The diagnosis uses the same `Body`
to say which Gaussians outside the silhouette float (`score.diagnosis`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Body:
    """An object's body: the largest cluster of its Gaussians, two Gaussians linked where their
    centres are nearer than the sum of their extents (each its largest scale, one standard
    deviation). Floaters labelled as the object that touch nothing of it fall outside the
    body."""

    members: np.ndarray  # [N] bool, the Gaussians of the body
    radius: float  # the median distance of its Gaussians from their median

    @classmethod
    def of(
        cls,
        means: np.ndarray,  # [N, 3]
        extents: np.ndarray,  # [N] each Gaussian's largest scale
        members: np.ndarray,  # [N] bool, the object's Gaussians
    ) -> Body:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        index = np.flatnonzero(members)
        body = np.zeros(len(means), bool)
        if index.size < 2:
            body[index] = True
            return cls(body, 1.0)
        points, reach = means[index], extents[index]
        # a linked pair is within twice the larger extent of the two: each Gaussian looks for
        # its partners no larger than itself within twice its own extent
        near = cKDTree(points).query_ball_point(points, 2 * reach)
        counts = np.fromiter(map(len, near), np.int64, len(near))
        first = np.repeat(np.arange(len(points)), counts)
        second = np.concatenate([np.asarray(js, np.int64) for js in near])
        gap = np.linalg.norm(points[first] - points[second], axis=1)
        keep = (reach[first] >= reach[second]) & (first != second)
        keep &= gap < reach[first] + reach[second]
        pairs = np.stack([first[keep], second[keep]], 1)
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


def extents(gaussians) -> np.ndarray:  # [N]
    """Each Gaussian's largest scale (one standard deviation), for `Body`."""
    return gaussians.scales.detach().float().amax(1).cpu().numpy()


def keep_bodies(
    means: torch.Tensor,  # [N, 3]
    reach: np.ndarray,  # [N] each Gaussian's largest scale (`extents`)
    labels: torch.Tensor,  # [N] int64, -1 unlabelled
) -> tuple[torch.Tensor, torch.Tensor]:  # [N] labels, [N] bool dropped
    """Each object label (>= 1) kept on its body only; its Gaussians outside the body become
    unlabelled. Background (0) and unlabelled Gaussians are left as they are."""
    out, dropped = labels.clone(), torch.zeros_like(labels, dtype=torch.bool)
    points = means.detach().float().cpu().numpy()
    known = labels.cpu().numpy()
    for k in np.unique(known[known > 0]).tolist():
        members = known == k
        off = members & ~Body.of(points, reach, members).members
        if off.any():
            rows = torch.from_numpy(np.flatnonzero(off)).to(labels.device)
            out[rows] = -1
            dropped[rows] = True
    return out, dropped
