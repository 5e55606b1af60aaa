"""Real spherical harmonics up to degree 3, evaluated as in the 3DGS reference (differentiable)."""

from __future__ import annotations

import torch
from torch import Tensor

from seggaussian.core.constants import MAX_SH_DEGREE, SH_C0, SH_C1, SH_C2, SH_C3


def sh_degree_of(sh: Tensor) -> int:  # sh: [N, num_sh_coeffs, 3]
    k = sh.shape[1]
    degree = int(round(k**0.5)) - 1
    if (degree + 1) ** 2 != k or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh has {k} coefficients per channel, expected (d+1)^2 for d in 0..{MAX_SH_DEGREE}")
    return degree


def sh_basis(
    dirs: Tensor,  # [N, 3] unit view directions (camera centre -> mean)
    degree: int,
) -> Tensor:  # [N, (degree + 1)^2]
    """The real SH basis of bands 0..degree at ``dirs``: column ``k`` multiplies coefficient ``sh[:, k]``
    (the 3DGS reference's polynomials and signs; differentiable in ``dirs``)."""
    x, y, z = (dirs[:, i : i + 1] for i in range(3))
    columns = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        columns += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        columns += [
            SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        columns += [
            SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.cat(columns, 1)


def evaluate_sh(
    sh: Tensor,  # [N, num_sh_coeffs, 3]
    dirs: Tensor,  # [N, 3] unit view directions (camera centre -> mean)
    degree: int,
) -> Tensor:  # [N, 3]
    """Sum of the SH basis times coefficients, for bands 0..degree (no +0.5 offset, no clamp).

    One product with the basis matrix: its backward writes the coefficients' gradient once. (Selecting each
    coefficient ``sh[:, k]`` would make autograd zero-fill a whole ``[N, K, 3]`` gradient per coefficient: 16 per
    render at degree 3, the largest cost of a CPU fit's backward pass.)
    """
    k = (degree + 1) ** 2
    basis = sh_basis(dirs, degree)  # [N, k]
    coeffs = sh if sh.shape[1] == k else sh[:, :k]
    return (basis.unsqueeze(-1) * coeffs).sum(1)


def sh_to_colors(
    sh: Tensor,  # [N, num_sh_coeffs, 3]
    view_dirs: Tensor,  # [N, 3]
    sh_degree: int | None = None,
) -> Tensor:  # [N, 3]
    """RGB = max(SH(dir) + 0.5, 0) as in 3DGS; ``sh_degree`` may be below the available degree."""
    available = sh_degree_of(sh)
    degree = available if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= available:
        raise ValueError(f"sh_degree={degree} but sh holds degree {available}")
    values = evaluate_sh(sh, view_dirs.to(sh.dtype), degree)
    return torch.clamp_min(values + 0.5, 0.0)
