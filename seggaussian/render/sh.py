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


def evaluate_sh(
    sh: Tensor,  # [N, num_sh_coeffs, 3]
    dirs: Tensor,  # [N, 3] unit view directions (camera centre -> mean)
    degree: int,
) -> Tensor:  # [N, 3]
    """Sum of the SH basis times coefficients, for bands 0..degree (no +0.5 offset, no clamp)."""
    out = SH_C0 * sh[:, 0]
    if degree < 1:
        return out
    x, y, z = (dirs[:, i : i + 1] for i in range(3))
    out = out - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree < 2:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (
        out
        + SH_C2[0] * xy * sh[:, 4]
        + SH_C2[1] * yz * sh[:, 5]
        + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
        + SH_C2[3] * xz * sh[:, 7]
        + SH_C2[4] * (xx - yy) * sh[:, 8]
    )
    if degree < 3:
        return out
    return (
        out
        + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
        + SH_C3[1] * xy * z * sh[:, 10]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
        + SH_C3[5] * z * (xx - yy) * sh[:, 14]
        + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
    )


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
