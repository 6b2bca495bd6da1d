"""Spherical harmonics: the renderers' monomial form against the term-by-term one."""

from __future__ import annotations

import pytest
import torch

from sagonline.render.sh import (
    BASIS,
    MONOMIALS,
    basis_matrix,
    eval_sh_monomials,
    eval_sh_terms,
    monomials,
    sh_basis,
)


@pytest.mark.parametrize("k", [1, 4, 9, 16])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_monomial_form_gives_the_terms_values_and_gradients(k, dtype):
    """Colours and both gradients (coefficients, directions) as the 3DGS terms give them, to
    float rounding; directions near the axes too (where a sign slip shows)."""
    gen = torch.Generator().manual_seed(k)
    dirs = torch.randn(500, 3, generator=gen, dtype=dtype)
    dirs[:6] = torch.eye(3, dtype=dtype).repeat(2, 1) * torch.tensor(
        [[1.0], [1], [1], [-1], [-1], [-1]], dtype=dtype
    )
    dirs = torch.nn.functional.normalize(dirs, dim=1)
    sh = torch.randn(500, k, 3, generator=gen, dtype=dtype)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    results = []
    for fn in (eval_sh_monomials, eval_sh_terms):
        s, d = sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)
        out = fn(s, d)
        weights = torch.linspace(-1, 1, out.numel(), dtype=dtype).view_as(out)
        (out * weights).sum().backward()
        results.append((out.detach(), s.grad, torch.zeros_like(d) if d.grad is None else d.grad))
    for ours, theirs in zip(*results, strict=True):
        torch.testing.assert_close(ours, theirs, atol=tol * 8, rtol=tol)


def test_each_basis_function_is_its_monomials():
    """The basis at x, y, z one at a time and at a mixed direction, by hand: Y_1 = -C1 y,
    Y_6 = C2[2] (2zz - xx - yy), Y_10 = C3[1] xyz."""
    from sagonline.render.sh import C1, C2, C3

    x, y, z = 0.3, -0.5, (1 - 0.3**2 - 0.5**2) ** 0.5
    basis = sh_basis(torch.tensor([[x, y, z]], dtype=torch.float64), 16)[0]
    assert float(basis[1]) == pytest.approx(-C1 * y)
    assert float(basis[6]) == pytest.approx(C2[2] * (2 * z * z - x * x - y * y))
    assert float(basis[10]) == pytest.approx(C3[1] * x * y * z)
    values = monomials(torch.tensor([[x, y, z]], dtype=torch.float64), 3)[0]
    for powers, value in zip(MONOMIALS, values.tolist(), strict=True):
        assert value == pytest.approx(x ** powers[0] * y ** powers[1] * z ** powers[2])
    assert len(set(MONOMIALS)) == 20 and basis_matrix(3).shape == (20, 16)
    assert sum(len(terms) for terms in BASIS) == int((basis_matrix(3) != 0).sum())
    with pytest.raises(ValueError, match="5 SH coefficients"):
        sh_basis(torch.zeros(1, 3), 5)
