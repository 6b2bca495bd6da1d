"""Real spherical harmonics up to degree 3, as in the 3DGS reference renderer.

`eval_sh_terms` writes the basis out term by term (the form to read against the 3DGS code; the
brute-force reference renderer and every CPU render use it). `eval_sh_monomials`, what `eval_sh`
runs on CUDA, computes the same basis as one fixed linear map of the direction's 20 monomials of
degree <= 3 (`monomials`, `basis_matrix`): a handful of tensor operations instead of about a
hundred, forward and backward (a GPU that renders a view or takes a fit step is bound by how
many kernels it launches).
"""

from __future__ import annotations

import functools

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

# Each basis function as {(power of x, power of y, power of z): coefficient}, in the order of
# the SH coefficients (`eval_sh_terms` is the same, term by term)
BASIS = (
    {(0, 0, 0): C0},
    {(0, 1, 0): -C1},
    {(0, 0, 1): C1},
    {(1, 0, 0): -C1},
    {(1, 1, 0): C2[0]},
    {(0, 1, 1): C2[1]},
    {(0, 0, 2): 2 * C2[2], (2, 0, 0): -C2[2], (0, 2, 0): -C2[2]},
    {(1, 0, 1): C2[3]},
    {(2, 0, 0): C2[4], (0, 2, 0): -C2[4]},
    {(2, 1, 0): 3 * C3[0], (0, 3, 0): -C3[0]},
    {(1, 1, 1): C3[1]},
    {(0, 1, 2): 4 * C3[2], (2, 1, 0): -C3[2], (0, 3, 0): -C3[2]},
    {(0, 0, 3): 2 * C3[3], (2, 0, 1): -3 * C3[3], (0, 2, 1): -3 * C3[3]},
    {(1, 0, 2): 4 * C3[4], (3, 0, 0): -C3[4], (1, 2, 0): -C3[4]},
    {(2, 0, 1): C3[5], (0, 2, 1): -C3[5]},
    {(3, 0, 0): C3[6], (1, 2, 0): -3 * C3[6]},
)
DEGREE_OF = {1: 0, 4: 1, 9: 2, 16: 3}  # coefficients per channel -> SH degree


# The monomials of degree <= 3 in x, y, z, as (power of x, power of y, power of z), in the
# order `monomials` builds them
MONOMIALS = (
    (0, 0, 0),
    *((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    *((2, 0, 0), (0, 2, 0), (0, 0, 2)),  # squares
    *((1, 1, 0), (0, 1, 1), (1, 0, 1)),  # each axis times the next
    *((3, 0, 0), (0, 3, 0), (0, 0, 3)),  # cubes
    *((2, 1, 0), (0, 2, 1), (1, 0, 2)),  # each square times the next axis
    *((2, 0, 1), (1, 2, 0), (0, 1, 2)),  # and times the one after
    (1, 1, 1),
)
COUNT = {0: 1, 1: 4, 2: 10, 3: 20}  # monomials of degree <= d


@functools.cache
def basis_matrix(degree: int) -> torch.Tensor:  # [monomials, (degree + 1) ** 2] float64
    """The constant map from the monomials of degree <= `degree` (`MONOMIALS`' first ones) to
    the SH basis up to `degree`."""
    row = {powers: i for i, powers in enumerate(MONOMIALS[: COUNT[degree]])}
    k = (degree + 1) ** 2
    matrix = torch.zeros(COUNT[degree], k, dtype=torch.float64)
    for column, terms in enumerate(BASIS[:k]):
        for powers, coefficient in terms.items():
            matrix[row[powers], column] = coefficient
    return matrix


def monomials(
    dirs: torch.Tensor,  # [N, 3]
    degree: int,  # 0-3
) -> torch.Tensor:  # [N, COUNT[degree]]
    """(N, M) the monomials of degree <= `degree` of each direction, in `MONOMIALS`' order."""
    parts = [torch.ones_like(dirs[:, :1]), dirs][: degree + 1]
    if degree >= 2:
        next_axis = dirs.roll(-1, dims=1)  # (y, z, x)
        squares = dirs * dirs
        parts += [squares, dirs * next_axis]
        if degree == 3:
            after = dirs.roll(-2, dims=1)  # (z, x, y)
            xyz = parts[3][:, :1] * dirs[:, 2:]
            parts += [squares * dirs, squares * next_axis, squares * after, xyz]
    return torch.cat(parts, dim=1)


def sh_basis(
    dirs: torch.Tensor,  # [N, 3] unit, camera -> point
    k: int,  # coefficients per channel: 1, 4, 9 or 16
) -> torch.Tensor:  # [N, k]
    """(N, k) the SH basis functions up to degree sqrt(k) - 1 at each direction."""
    if k not in DEGREE_OF:
        raise ValueError(f"{k} SH coefficients per channel: use 1, 4, 9 or 16")
    degree = DEGREE_OF[k]
    return monomials(dirs, degree) @ basis_matrix(degree).to(dirs)


def eval_sh(
    sh: torch.Tensor,  # [N, K, 3], K in 1, 4, 9, 16
    dirs: torch.Tensor,  # [N, 3] unit, camera -> point
) -> torch.Tensor:  # [N, 3] RGB
    """Colour from SH coefficients: (N, 3) RGB = SH(dir) + 0.5, clamped below at 0.

    sh: (N, K, 3) with K in {1, 4, 9, 16}; dirs: (N, 3) unit view directions (camera -> point).
    On CUDA `eval_sh_monomials` (a handful of kernels where the terms launch about a hundred);
    elsewhere `eval_sh_terms`, as every committed CPU fit was made (the two agree to float
    rounding, and a fit amplifies rounding: the same fit would not come back to the hundredth).
    """
    return eval_sh_monomials(sh, dirs) if sh.is_cuda else eval_sh_terms(sh, dirs)


def eval_sh_monomials(
    sh: torch.Tensor,  # [N, K, 3], K in 1, 4, 9, 16
    dirs: torch.Tensor,  # [N, 3] unit, camera -> point
) -> torch.Tensor:  # [N, 3] RGB
    """`eval_sh` with the basis as one linear map of the direction's monomials (`sh_basis`)."""
    if sh.shape[1] == 1:
        return (C0 * sh[:, 0] + 0.5).clamp_min(0.0)
    basis = sh_basis(dirs.to(sh.dtype), sh.shape[1])  # [N, K]
    return (torch.bmm(basis[:, None, :], sh)[:, 0] + 0.5).clamp_min(0.0)


def eval_sh_terms(
    sh: torch.Tensor,  # [N, K, 3], K in 1, 4, 9, 16
    dirs: torch.Tensor,  # [N, 3] unit, camera -> point
) -> torch.Tensor:  # [N, 3] RGB
    """`eval_sh` written out term by term, degree by degree, as the 3DGS reference renderer has
    it (the brute-force reference renderer and the tests use it)."""
    k = sh.shape[1]
    out = C0 * sh[:, 0]
    if k > 1:
        x, y, z = (dirs[:, i : i + 1] for i in range(3))
        out = out - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
        if k > 4:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            out = (
                out
                + C2[0] * xy * sh[:, 4]
                + C2[1] * yz * sh[:, 5]
                + C2[2] * (2 * zz - xx - yy) * sh[:, 6]
                + C2[3] * xz * sh[:, 7]
                + C2[4] * (xx - yy) * sh[:, 8]
            )
            if k > 9:
                out = (
                    out
                    + C3[0] * y * (3 * xx - yy) * sh[:, 9]
                    + C3[1] * xy * z * sh[:, 10]
                    + C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
                    + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
                    + C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
                    + C3[5] * z * (xx - yy) * sh[:, 14]
                    + C3[6] * x * (xx - 3 * yy) * sh[:, 15]
                )
    return (out + 0.5).clamp_min(0.0)
