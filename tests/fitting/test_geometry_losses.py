"""2DGS's regularisers: the depth distortion equals its pairwise definition, the normal
consistency vanishes on a flat surfel facing the camera, and both take the same gradients through
the compiled kernel as through autograd over the PyTorch path."""

from __future__ import annotations

import math
import shutil
from collections import defaultdict

import pytest
import torch

from sagonline.fitting.losses import (
    depth_distortion,
    depth_normals,
    normal_consistency,
    splat_geometry,
)
from sagonline.render.rasterize import rasterize
from sagonline.render.reference import reference_render
from sagonline.scene.cameras import intrinsics, make_camera
from sagonline.scene.gaussians import Gaussians
from tests.fixtures import random_gaussians, small_camera

NEAR, FAR = 1.0, 8.0
LEAVES = ("means", "quats", "scales", "opacities", "sh")


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_distortion_is_the_pairwise_sum_over_each_ray(kind):
    g = random_gaussians(40, kind, seed=5)
    cam = small_camera(20, 15)
    geometry = splat_geometry(g, cam, NEAR, FAR)
    out = rasterize(g, cam, features=geometry)
    per_pixel = out.alpha * out.features[..., 4] - out.features[..., 3] ** 2
    # the brute-force renderer's trace lists every composited (pixel, splat, T_i, alpha_i)
    ref = reference_render(g, cam, trace_eps=0.0)
    m = geometry[:, 3].double()
    rays = defaultdict(list)
    for pixel, splat, T, alpha, _ in ref.trace:
        rays[pixel].append((alpha * T, float(m[splat])))
    expected = torch.zeros(cam.height * cam.width, dtype=torch.float64)
    for pixel, pairs in rays.items():
        expected[pixel] = sum(
            wi * wj * (mi - mj) ** 2
            for i, (wi, mi) in enumerate(pairs)
            for wj, mj in pairs[i + 1 :]
        )
    assert float(expected.max()) > 1e-3  # rays cross several depths: something to match
    torch.testing.assert_close(per_pixel.flatten().double(), expected, atol=2e-5, rtol=1e-3)
    torch.testing.assert_close(
        depth_distortion(out.alpha, out.features[..., 3], out.features[..., 4]),
        expected.clamp_min(0).mean().float(),
        atol=1e-6,
        rtol=1e-3,
    )


def _wall(tilt: float) -> tuple[Gaussians, object]:
    """One large opaque surfel 4 units in front of the camera, turned by `tilt` about y."""
    half = tilt / 2
    quat = torch.tensor([[math.cos(half), 0.0, math.sin(half), 0.0]])
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 4.0]]),
        quats=quat,
        scales=torch.tensor([[1.0, 1.0]]),
        opacities=torch.tensor([0.99]),
        sh=torch.full((1, 1, 3), 0.5),
    )
    cam = make_camera(intrinsics(30.0, 30.0, 16.0, 12.0), torch.eye(4), 32, 24, "front")
    return g, cam


@pytest.mark.parametrize("tilt", [0.0, 0.5])
def test_normal_consistency_vanishes_on_a_flat_surface(tilt):
    g, cam = _wall(tilt)
    geometry = splat_geometry(g, cam, NEAR, FAR)
    expected = torch.tensor([-math.sin(tilt), 0.0, -math.cos(tilt)])
    torch.testing.assert_close(geometry[0, :3], expected, atol=1e-6, rtol=0)
    out = rasterize(g, cam, features=geometry)
    inner = (slice(6, 18), slice(8, 24))  # well inside the surfel's support
    normals = depth_normals(out.depth, out.alpha, cam)[inner]
    torch.testing.assert_close(normals, expected.expand_as(normals), atol=2e-3, rtol=0)
    rendered = out.features[..., :3] / out.alpha[..., None]
    torch.testing.assert_close(rendered[inner], expected.expand_as(normals), atol=1e-5, rtol=0)
    # splats turned 60 degrees away from the surface their depths describe cost more
    aligned = normal_consistency(out.features[..., :3], out.depth, out.alpha, cam)
    turned = geometry.clone()
    turned[:, :3] = torch.tensor([math.sin(tilt + 1.0), 0.0, -math.cos(tilt + 1.0)])
    off = rasterize(g, cam, features=turned).features[..., :3]
    assert float(normal_consistency(off, out.depth, out.alpha, cam)) > float(aligned) + 0.05


@pytest.mark.skipif(
    shutil.which("c++") is None and shutil.which("g++") is None, reason="no C++ compiler"
)
@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_regulariser_gradients_through_the_kernel_match_autograd(kind):
    from sagonline.render.native import rasterize_native

    g0 = random_gaussians(50, kind, seed=7)
    cam = small_camera(36, 27)

    def grads(fn):
        leaves = {k: getattr(g0, k).clone().requires_grad_(True) for k in LEAVES}
        g = Gaussians(**leaves)
        out = fn(g, cam, features=splat_geometry(g, cam, NEAR, FAR))
        loss = 10 * depth_distortion(out.alpha, out.features[..., 3], out.features[..., 4])
        loss = loss + normal_consistency(out.features[..., :3], out.depth, out.alpha, cam)
        loss.backward()
        return float(loss.detach()), {k: v.grad for k, v in leaves.items()}

    ref_loss, ref = grads(rasterize)
    nat_loss, nat = grads(rasterize_native)
    assert nat_loss == pytest.approx(ref_loss, rel=1e-4)
    for k in ("means", "quats", "scales", "opacities"):
        scale = float(ref[k].abs().max())
        assert scale > 0, k
        torch.testing.assert_close(nat[k], ref[k], atol=1e-4 * scale, rtol=1e-3)


def test_the_neighbour_consistency_is_least_at_the_scenes_own_depth():
    from sagonline.fitting.losses import nearest_views, neighbour_consistency
    from sagonline.scene.generator import make_scene

    s = make_scene(layout="forward", num_gaussians=3000, width=64, height=48, num_train_views=5)
    cams = s.train_cameras
    near = nearest_views(cams)
    assert all(len(n) == 2 and i not in n for i, n in enumerate(near))
    outs = [rasterize(s.gaussians, c) for c in cams]
    photos = [o.rgb.clamp(0, 1) for o in outs]
    me, others = 2, [(cams[j], photos[j]) for j in near[2]]

    def error(scale: float, neighbours=others) -> torch.Tensor:
        depth = (outs[me].depth * scale).requires_grad_(True)
        loss = neighbour_consistency(depth, outs[me].alpha, photos[me], cams[me], neighbours)
        loss.backward()
        assert torch.isfinite(depth.grad).all()
        return loss.detach()

    own = error(1.0)
    assert own < error(0.8) and own < error(1.25)  # nearer or farther fetches other colours
    assert error(1.0, neighbours=[]) == 0  # no neighbour: nothing to compare
