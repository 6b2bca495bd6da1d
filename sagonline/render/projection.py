"""Per-Gaussian screen-space quantities for one camera, and the per-pixel splat response.

Two primitive kinds share one interface:
- 3DGS: EWA splatting. 2D covariance J W Sigma W^T J^T plus a 0.3 px^2 low-pass, evaluated as
  alpha = o * exp(-d^T Sigma2d^-1 d / 2).
- 2DGS: exact ray-splat intersection. The surfel's local (u, v) plane maps to homogeneous pixels
  by M = K [R t_u s_u | R t_v s_v | R mu + t]; the pixel's two planes (x m2 - m0, y m2 - m1)
  meet the surfel at (u, v) = cross(k, l)[:2] / cross(k, l)[2]; rho3d = u^2 + v^2, with the
  2DGS screen-space filter rho2d = 2 |d|^2 and rho = min(rho3d, rho2d).

Support: a Gaussian reaches a pixel only where its Mahalanobis radius is at most 3
(power >= -4.5), the same ellipse its screen bounding box encloses, so results never depend on
tiling.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from sagonline.render.sh import eval_sh
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians, quat_to_rotmat

SIGMA_CUTOFF = 3.0
LOW_PASS = 0.3  # px^2 added to every 3DGS 2D covariance
SURFEL_FILTER_INV_SQ = 2.0  # 2DGS screen-space filter: rho2d = 2 |d|^2
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99


@dataclass
class ProjectedSplats:
    """Gaussians that survive culling for one camera (M of the original N).

    ids: (M,) indices into the original Gaussians; means2d: (M, 2) projected centres in pixels;
    depths: (M,) camera-space z of the centres (the sort key); bbox: (M, 4) xmin, xmax, ymin,
    ymax in pixels; opacities: (M,); colors: (M, 3) SH evaluated for this view;
    conics: (M, 3) inverse 2D covariance (a, b, c) for 3DGS; transforms: (M, 3, 3) M for 2DGS.
    """

    kind: str
    ids: torch.Tensor
    means2d: torch.Tensor
    depths: torch.Tensor
    bbox: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    conics: torch.Tensor | None = None
    transforms: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.ids.shape[0]

    def params(
        self,
    ) -> torch.Tensor:  # [M, P] packed per splat
        """(M, P) packed per-splat parameters consumed by `splat_response`."""
        shape_params = self.conics if self.kind == "3dgs" else self.transforms.reshape(-1, 9)
        return torch.cat(
            [self.means2d, self.opacities[:, None], self.depths[:, None], shape_params], dim=1
        )


def project(
    gaussians: Gaussians, camera: Camera, near: float = 0.01, with_colors: bool = True
) -> ProjectedSplats:
    """Project, cull (behind `near`, degenerate, off-screen) and shade for one camera."""
    g, cam = gaussians, camera.to(gaussians.device)
    R, t = cam.rotation, cam.translation
    p_cam = g.means @ R.T + t
    z = p_cam[:, 2]
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    rot = quat_to_rotmat(g.quats)
    if g.kind == "3dgs":
        valid, means2d, bbox, extra = _project_ellipsoids(g, rot, R, p_cam, fx, fy, cx, cy, cam)
    else:
        valid, means2d, bbox, extra = _project_surfels(g, rot, R, p_cam, cam.K)
    valid = valid & (z > near)
    on_screen = (bbox[:, 1] > 0) & (bbox[:, 0] < cam.width)
    on_screen = on_screen & (bbox[:, 3] > 0) & (bbox[:, 2] < cam.height)
    valid = valid & on_screen
    valid = valid & (g.opacities >= ALPHA_MIN)
    ids = torch.nonzero(valid).squeeze(1)
    colors = view_colors(g, ids, cam.center) if with_colors else torch.zeros(0, 3, device=g.device)
    out = ProjectedSplats(
        kind=g.kind,
        ids=ids,
        means2d=means2d[ids],
        depths=z[ids],
        bbox=bbox[ids],
        opacities=g.opacities[ids],
        colors=colors,
    )
    if g.kind == "3dgs":
        out.conics = extra[ids]
    else:
        out.transforms = extra[ids]
    return out


def view_colors(
    gaussians: Gaussians,
    ids: torch.Tensor | None,  # [M] indices of the Gaussians to shade; None: all of them
    center: torch.Tensor,  # [3] the camera's centre, world coordinates
) -> torch.Tensor:  # [M, 3]
    """(M, 3) the SH colours of Gaussians `ids` (all with None) seen from the camera's centre."""
    means, sh = (
        (gaussians.means, gaussians.sh)
        if ids is None
        else (gaussians.means[ids], gaussians.sh[ids])
    )
    dirs = means - center
    dirs = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return eval_sh(sh, dirs)


def _project_ellipsoids(g, rot, R, p_cam, fx, fy, cx, cy, cam):
    z = p_cam[:, 2].clamp_min(1e-6)
    # Clamp the Jacobian's evaluation point to 1.3x the view frustum, as the 3DGS renderer does.
    lim_xp = (cam.width - cx) / fx + 0.3 * cam.width / (2 * fx)
    lim_xn = cx / fx + 0.3 * cam.width / (2 * fx)
    lim_yp = (cam.height - cy) / fy + 0.3 * cam.height / (2 * fy)
    lim_yn = cy / fy + 0.3 * cam.height / (2 * fy)
    tx = torch.clamp(p_cam[:, 0] / z, -lim_xn, lim_xp) * z
    ty = torch.clamp(p_cam[:, 1] / z, -lim_yn, lim_yp) * z
    zeros = torch.zeros_like(z)
    J = torch.stack(
        [
            torch.stack([fx / z, zeros, -fx * tx / (z * z)], dim=1),
            torch.stack([zeros, fy / z, -fy * ty / (z * z)], dim=1),
        ],
        dim=1,
    )  # (N, 2, 3)
    M = rot * g.scales[:, None, :]  # R S
    cov_world = M @ M.transpose(1, 2)
    cov_cam = R @ cov_world @ R.T
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    a = cov2d[:, 0, 0] + LOW_PASS
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + LOW_PASS
    det = a * c - b * b
    valid = det > 0
    det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], dim=1)
    means2d = torch.stack([fx * p_cam[:, 0] / z + cx, fy * p_cam[:, 1] / z + cy], dim=1)
    ext_x = SIGMA_CUTOFF * a.clamp_min(0).sqrt()
    ext_y = SIGMA_CUTOFF * c.clamp_min(0).sqrt()
    bbox = torch.stack(
        [
            means2d[:, 0] - ext_x,
            means2d[:, 0] + ext_x,
            means2d[:, 1] - ext_y,
            means2d[:, 1] + ext_y,
        ],
        dim=1,
    )
    valid = valid & (torch.isfinite(bbox).all(1))
    return valid, means2d, bbox, conics


def _project_surfels(g, rot, R, p_cam, K):
    tu = (rot[:, :, 0] * g.scales[:, :1]) @ R.T
    tv = (rot[:, :, 1] * g.scales[:, 1:2]) @ R.T
    M = K @ torch.stack([tu, tv, p_cam], dim=2)  # (N, 3, 3): columns u, v, centre
    w = M[:, 2, 2]
    means2d = M[:, :2, 2] / w.clamp_min(1e-6)[:, None]
    # Bounding box of the 3-sigma disc's image via its dual conic D = M diag(9, 9, -1) M^T.
    q = torch.tensor([SIGMA_CUTOFF**2, SIGMA_CUTOFF**2, -1.0], device=M.device)
    D = (M * q) @ M.transpose(1, 2)
    d22 = D[:, 2, 2]
    valid = d22 < 0  # else the disc crosses the camera plane: its image is not bounded
    d22s = torch.where(valid, d22, -torch.ones_like(d22))
    cx, cy = D[:, 0, 2] / d22s, D[:, 1, 2] / d22s
    hx = ((D[:, 0, 2] ** 2 - D[:, 0, 0] * D[:, 2, 2]).clamp_min(0)).sqrt() / d22s.abs()
    hy = ((D[:, 1, 2] ** 2 - D[:, 1, 1] * D[:, 2, 2]).clamp_min(0)).sqrt() / d22s.abs()
    r_filter = SIGMA_CUTOFF / SURFEL_FILTER_INV_SQ**0.5
    bbox = torch.stack(
        [
            torch.minimum(cx - hx, means2d[:, 0] - r_filter),
            torch.maximum(cx + hx, means2d[:, 0] + r_filter),
            torch.minimum(cy - hy, means2d[:, 1] - r_filter),
            torch.maximum(cy + hy, means2d[:, 1] + r_filter),
        ],
        dim=1,
    )
    valid = valid & (torch.isfinite(bbox).all(1))
    return valid, means2d, bbox, M


def reach_boxes(
    proj: ProjectedSplats,
) -> torch.Tensor:  # [M, 4] xmin, xmax, ymin, ymax
    """(M, 4) boxes bounding where each splat's alpha reaches 1/255: the 3-sigma boxes shrunk
    to the Mahalanobis radius^2 min(9, 2 ln(255 opacity) + 2e-3) (the compiled CPU kernel's
    boxes; the margin keeps float rounding at the edge inside). A faint splat is then listed
    only in the tiles it can change: the same images and votes from fewer splat-tile pairs."""
    r2 = (2.0 * torch.log(proj.opacities / ALPHA_MIN) + 2e-3).clamp(max=SIGMA_CUTOFF**2)
    if proj.kind == "3dgs":
        scale = (r2 / SIGMA_CUTOFF**2).sqrt()
        half_x = 0.5 * (proj.bbox[:, 1] - proj.bbox[:, 0]) * scale
        half_y = 0.5 * (proj.bbox[:, 3] - proj.bbox[:, 2]) * scale
        mx, my = proj.means2d[:, 0], proj.means2d[:, 1]
        return torch.stack([mx - half_x, mx + half_x, my - half_y, my + half_y], dim=1)
    M = proj.transforms
    q = torch.stack([r2, r2, -torch.ones_like(r2)], dim=1)
    D = (M * q[:, None, :]) @ M.transpose(1, 2)
    d22 = D[:, 2, 2]  # < 0: it was with radius 3, and a smaller disc keeps it so
    cx, cy = D[:, 0, 2] / d22, D[:, 1, 2] / d22
    hx = ((D[:, 0, 2] ** 2 - D[:, 0, 0] * d22).clamp_min(0)).sqrt() / d22.abs()
    hy = ((D[:, 1, 2] ** 2 - D[:, 1, 1] * d22).clamp_min(0)).sqrt() / d22.abs()
    r_filter = (r2 / SURFEL_FILTER_INV_SQ).sqrt()
    mx, my = proj.means2d[:, 0], proj.means2d[:, 1]
    return torch.stack(
        [
            torch.minimum(cx - hx, mx - r_filter),
            torch.maximum(cx + hx, mx + r_filter),
            torch.minimum(cy - hy, my - r_filter),
            torch.maximum(cy + hy, my + r_filter),
        ],
        dim=1,
    )


def splat_response(
    kind: str,
    params: torch.Tensor,  # [..., B, P] packed splats
    px: torch.Tensor,  # [..., 1, Q]
    py: torch.Tensor,  # [..., 1, Q]
):
    """Alpha of gathered splats at pixel centres.

    params: (..., B, K) packed splat parameters (see `ProjectedSplats.params`), broadcast against
    px, py: (..., 1, Q) pixel-centre coordinates. Returns alpha, depth (camera z where the ray
    meets the splat; the centre's z for 3DGS) and squared distance to the projected centre, each
    (..., B, Q). alpha is 0 outside the 3-sigma support, below 1/255, or behind the near plane
    (2DGS), and at most 0.99.
    """
    mx, my, opac, depth = (params[..., i : i + 1] for i in range(4))
    dx, dy = px - mx, py - my
    dist2 = dx * dx + dy * dy
    if kind == "3dgs":
        a, b, c = (params[..., 4 + i : 5 + i] for i in range(3))
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        inside = power >= -0.5 * SIGMA_CUTOFF**2
        depth_px = depth.expand_as(power)
    else:
        m = [params[..., 4 + i : 5 + i] for i in range(9)]
        k0, k1, k2 = px * m[6] - m[0], px * m[7] - m[1], px * m[8] - m[2]
        l0, l1, l2 = py * m[6] - m[3], py * m[7] - m[4], py * m[8] - m[5]
        pz = k0 * l1 - k1 * l0
        pz = torch.where(pz.abs() < 1e-12, torch.full_like(pz, 1e-12), pz)
        u = (k1 * l2 - k2 * l1) / pz
        v = (k2 * l0 - k0 * l2) / pz
        rho3d = u * u + v * v
        rho2d = SURFEL_FILTER_INV_SQ * dist2
        use3d = rho3d <= rho2d
        rho = torch.where(use3d, rho3d, rho2d)
        depth_px = torch.where(use3d, u * m[6] + v * m[7] + m[8], depth.expand_as(rho))
        power = -0.5 * rho
        inside = (rho <= SIGMA_CUTOFF**2) & (depth_px > 1e-2)
    alpha = (opac * torch.exp(power)).clamp_max(ALPHA_MAX)
    alpha = torch.where(inside & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    return alpha, depth_px, dist2


def depth_rank(
    proj: ProjectedSplats,
) -> torch.Tensor:  # [M]
    """(M,) each projected splat's place in front-to-back order (ties keep projection order)."""
    m = len(proj)
    rank = torch.empty(m, dtype=torch.long, device=proj.depths.device)
    rank[torch.sort(proj.depths, stable=True).indices] = torch.arange(m, device=rank.device)
    return rank
