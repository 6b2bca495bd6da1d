"""Brute-force per-pixel rasterizer: slow, float64, and written to be obviously correct.

It shares no code with the fast path beyond SH evaluation: every pixel loops over every Gaussian
sorted by centre depth, computes its alpha from first principles (EWA 2D covariance for 3DGS, a
world-space ray-plane intersection for 2DGS surfels) and composites front to back with the
3DGS rules. Used only by tests, on tiny scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sagonline.render.sh import eval_sh_terms
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

ALPHA_MIN, ALPHA_MAX, CUTOFF2 = 1.0 / 255.0, 0.99, 9.0


@dataclass
class ReferenceRender:
    rgb: np.ndarray  # (H, W, 3)
    alpha: np.ndarray  # (H, W)
    depth: np.ndarray  # (H, W)
    features: np.ndarray | None  # (H, W, F)
    ids: np.ndarray  # (H, W)
    trace: list[tuple[int, int, float, float, float]]  # pixel, gaussian, T_i, alpha_i, distance


def _rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def reference_render(
    gaussians: Gaussians,
    camera: Camera,
    *,
    features: torch.Tensor | None = None,  # [N, F]
    background=(0.0, 0.0, 0.0),
    t_stop: float = 0.0001,
    trace_eps: float = 0.01,
    near: float = 0.01,
) -> ReferenceRender:
    """Brute force in float64: every pixel against every Gaussian, front to back.

    Why one function: the oracle the tests trust is written straight through, pixel by pixel,
    so it reads against the method's definition without a detour."""
    g = gaussians.to("cpu")
    means = g.means.double().numpy()
    quats = g.quats.double().numpy()
    scales = g.scales.double().numpy()
    opac = g.opacities.double().numpy()
    n = len(g)
    K = camera.K.double().numpy()
    Rw = camera.world_to_cam[:3, :3].double().numpy()
    tw = camera.world_to_cam[:3, 3].double().numpy()
    center = -Rw.T @ tw
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W, H = camera.width, camera.height
    dirs = means - center
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    colors = eval_sh_terms(g.sh.double(), torch.from_numpy(dirs)).numpy()
    feats = None if features is None else features.double().cpu().numpy()
    p_cam = means @ Rw.T + tw
    order = np.argsort(p_cam[:, 2], kind="stable")
    mean2d = np.stack([fx * p_cam[:, 0] / p_cam[:, 2] + cx, fy * p_cam[:, 1] / p_cam[:, 2] + cy], 1)

    # Per-Gaussian setup.
    alive = (p_cam[:, 2] > near) & (opac >= ALPHA_MIN)
    conics = np.zeros((n, 2, 2))
    normals = np.zeros((n, 3))
    tangents = np.zeros((n, 2, 3))
    for i in range(n):
        R = _rotation(quats[i])
        if g.kind == "3dgs":
            x, y, z = p_cam[i]
            lim_x = ((W - cx) / fx + 0.15 * W / fx, cx / fx + 0.15 * W / fx)
            lim_y = ((H - cy) / fy + 0.15 * H / fy, cy / fy + 0.15 * H / fy)
            x = min(max(x / z, -lim_x[1]), lim_x[0]) * z
            y = min(max(y / z, -lim_y[1]), lim_y[0]) * z
            J = np.array([[fx / z, 0, -fx * x / z**2], [0, fy / z, -fy * y / z**2]])
            sigma = R @ np.diag(scales[i] ** 2) @ R.T
            cov = J @ Rw @ sigma @ Rw.T @ J.T + 0.3 * np.eye(2)
            conics[i] = np.linalg.inv(cov)
        else:
            tangents[i] = (R[:, :2] * scales[i]).T  # world tangent vectors scaled by s_u, s_v
            normals[i] = R[:, 2]
            tz = Rw[2] @ tangents[i].T  # camera z of the two tangents
            alive[i] &= p_cam[i, 2] > 3.0 * np.hypot(tz[0], tz[1])

    rgb = np.zeros((H, W, 3))
    alpha_img = np.zeros((H, W))
    depth_img = np.zeros((H, W))
    feat_img = None if feats is None else np.zeros((H, W, feats.shape[1]))
    ids = -np.ones((H, W), dtype=np.int64)
    trace: list[tuple[int, int, float, float, float]] = []
    K_inv = np.linalg.inv(K)
    for yy in range(H):
        for xx in range(W):
            pix = np.array([xx + 0.5, yy + 0.5])
            ray_cam = K_inv @ np.array([pix[0], pix[1], 1.0])
            ray_world = Rw.T @ ray_cam
            T, best = 1.0, 0.0
            for i in order:
                if not alive[i]:
                    continue
                d = pix - mean2d[i]
                if g.kind == "3dgs":
                    m2 = d @ conics[i] @ d
                    z_hit = p_cam[i, 2]
                else:
                    denom = ray_world @ normals[i]
                    rho3d = np.inf
                    if abs(denom) > 1e-15:
                        s = ((means[i] - center) @ normals[i]) / denom
                        hit = center + s * ray_world
                        u = (hit - means[i]) @ tangents[i][0] / (scales[i, 0] ** 2)
                        v = (hit - means[i]) @ tangents[i][1] / (scales[i, 1] ** 2)
                        rho3d = u * u + v * v
                    rho2d = 2.0 * (d @ d)
                    m2 = min(rho3d, rho2d)
                    z_hit = (Rw @ hit + tw)[2] if rho3d <= rho2d else p_cam[i, 2]
                    if z_hit <= 1e-2:
                        continue
                if m2 > CUTOFF2:
                    continue
                a = min(ALPHA_MAX, opac[i] * np.exp(-0.5 * m2))
                if a < ALPHA_MIN:
                    continue
                if trace_eps < T:
                    trace.append((yy * W + xx, int(i), T, a, float(np.sqrt(d @ d))))
                if T * (1 - a) < t_stop:
                    break
                w = a * T
                rgb[yy, xx] += w * colors[i]
                depth_img[yy, xx] += w * z_hit
                if feat_img is not None:
                    feat_img[yy, xx] += w * feats[i]
                if w > best:
                    best, ids[yy, xx] = w, i
                T *= 1 - a
            alpha_img[yy, xx] = 1 - T
            rgb[yy, xx] += T * np.asarray(background, dtype=np.float64)
    return ReferenceRender(rgb, alpha_img, depth_img, feat_img, ids, trace)
