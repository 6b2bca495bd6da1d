"""Quaternions to rotations and to a surfel's normal."""

from __future__ import annotations

import torch


def test_a_surfels_normal_is_its_rotations_third_column_bit_for_bit():
    """`quat_to_normal` (the fit's 2DGS normals, three entries instead of nine) gives exactly
    `quat_to_rotmat`'s third column, and the same gradient: the CPU fits stay bit for bit."""
    from sagonline.scene.gaussians import quat_to_normal, quat_to_rotmat

    quats = torch.nn.functional.normalize(torch.randn(300, 4), dim=1)
    ours, theirs = quats.clone().requires_grad_(True), quats.clone().requires_grad_(True)
    weights = torch.randn(300, 3)
    normal, column = quat_to_normal(ours), quat_to_rotmat(theirs)[:, :, 2]
    assert torch.equal(normal, column)
    (normal * weights).sum().backward()
    (column * weights).sum().backward()
    assert torch.equal(ours.grad, theirs.grad)
