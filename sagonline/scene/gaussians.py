"""The Gaussian scene model: activated parameters only (raw PLY values live in `scene.io`).

Conventions (fixed once for the whole library):
- `means` (N, 3) world coordinates.
- `quats` (N, 4) unit quaternions, w x y z order.
- `scales` (N, 3) positive standard deviations for 3DGS ellipsoids, or (N, 2) for 2DGS surfels
  (tangent-plane extents; the surfel normal is the third rotation column).
- `opacities` (N,) in [0, 1].
- `sh` (N, K, 3) spherical-harmonic colour coefficients, K = (degree + 1) ** 2; `sh[:, 0]` is DC.
- `normals` (N, 3) or None: carried through file round trips, unused by rendering.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

SH_C0 = 0.28209479177387814


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    degree = round(num_coeffs**0.5) - 1
    if (degree + 1) ** 2 != num_coeffs or degree < 0:
        raise ValueError(f"{num_coeffs} SH coefficients per channel is not (degree+1)^2")
    return degree


@dataclass
class Gaussians:
    """A set of N Gaussians (3DGS) or surfels (2DGS) with activated parameters."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    normals: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        checks = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "opacities": (self.opacities, (n,)),
        }
        for name, (t, shape) in checks.items():
            if tuple(t.shape) != shape:
                raise ValueError(f"Gaussians.{name} has shape {tuple(t.shape)}, expected {shape}")
        if self.scales.ndim != 2 or self.scales.shape[0] != n or self.scales.shape[1] not in (2, 3):
            raise ValueError(
                f"Gaussians.scales has shape {tuple(self.scales.shape)}, "
                f"expected ({n}, 3) for 3DGS or ({n}, 2) for 2DGS"
            )
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh has shape {tuple(self.sh.shape)}, expected ({n}, K, 3)")
        sh_degree_from_coeffs(self.sh.shape[1])
        if self.normals is not None and tuple(self.normals.shape) != (n, 3):
            raise ValueError(f"Gaussians.normals has shape {tuple(self.normals.shape)}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def kind(self) -> str:
        """'2dgs' for surfels (two scales), '3dgs' for ellipsoids."""
        return "2dgs" if self.scales.shape[1] == 2 else "3dgs"

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    def to(self, device: torch.device | str) -> Gaussians:
        return self._map(lambda t: t.to(device))

    def subset(
        self,
        index: torch.Tensor,  # [N] bool, or [M] indices
    ) -> Gaussians:
        """Gaussians selected by a boolean mask or index tensor."""
        return self._map(lambda t: t[index])

    def _map(self, fn) -> Gaussians:
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return replace(self, **{k: (fn(v) if v is not None else None) for k, v in values.items()})

    def bounding_box(
        self,
    ) -> tuple[torch.Tensor, torch.Tensor]:  # [3] min, [3] max
        return self.means.min(dim=0).values, self.means.max(dim=0).values


def quat_to_rotmat(
    quats: torch.Tensor,  # [N, 4] unit wxyz
) -> torch.Tensor:  # [N, 3, 3]
    """(N, 4) unit wxyz quaternions -> (N, 3, 3) rotation matrices."""
    w, x, y, z = quats.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*quats.shape[:-1], 3, 3)


def quat_to_normal(
    quats: torch.Tensor,  # [N, 4] unit wxyz
) -> torch.Tensor:  # [N, 3]
    """(N, 3) the third column of `quat_to_rotmat` (a surfel's normal), by the same expressions
    (so the same values) without the other six entries and their backward."""
    w, x, y, z = quats.unbind(-1)
    return torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)


def rotmat_to_quat(
    rot: torch.Tensor,  # [N, 3, 3]
) -> torch.Tensor:  # [N, 4] unit wxyz, w >= 0
    """(N, 3, 3) rotation matrices -> (N, 4) unit wxyz quaternions (w >= 0)."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(rot.detach().cpu().double().numpy()).as_quat()
    q = torch.as_tensor(xyzw, dtype=rot.dtype)[:, [3, 0, 1, 2]]
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.to(rot.device)
