"""Real spherical harmonics up to degree 3, evaluated as in the 3DGS reference (differentiable).

``evaluate_sh`` contracts the basis (``sh_basis``, torch: differentiable in the directions) with the coefficients in
one compiled pass per direction (``_contract_forward`` / ``_contract_backward``, numba, parallel over Gaussians; each
Gaussian's sum in coefficient order, the same for any thread count). ``evaluate_sh_reference`` is the plain torch
sum, one coefficient at a time: the reference the tests compare against.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from seggaussian.core.constants import MAX_SH_DEGREE
from seggaussian.frames.sh_rotation import basis_columns
from seggaussian.render.parallel import GAUSSIANS_PER_CHUNK, run_parallel


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
    (the polynomials of ``frames.sh_rotation.basis_columns``, in torch: differentiable in ``dirs``)."""
    x, y, z = (dirs[:, i : i + 1] for i in range(3))
    return torch.cat(basis_columns(x, y, z, torch.ones_like(x), degree), 1)


@numba.njit(parallel=True, cache=True, nogil=True)
def _contract_forward(basis, coeffs, out):
    """``out[n, c] = sum_k basis[n, k] coeffs[n, k, c]`` over the basis' K columns (``coeffs`` may hold more)."""
    for n in prange(basis.shape[0]):
        a0 = a1 = a2 = basis.dtype.type(0.0)
        for k in range(basis.shape[1]):
            b = basis[n, k]
            a0 += b * coeffs[n, k, 0]
            a1 += b * coeffs[n, k, 1]
            a2 += b * coeffs[n, k, 2]
        out[n, 0], out[n, 1], out[n, 2] = a0, a1, a2


@numba.njit(parallel=True, cache=True, nogil=True)
def _contract_backward(basis, coeffs, grad, g_basis, g_coeffs):
    """Gradients of ``_contract_forward``: ``g_coeffs[n, k] = basis[n, k] grad[n]`` (zero beyond the basis' K columns),
    ``g_basis[n, k] = grad[n] . coeffs[n, k]``."""
    for n in prange(basis.shape[0]):
        g0, g1, g2 = grad[n, 0], grad[n, 1], grad[n, 2]
        for k in range(basis.shape[1]):
            b = basis[n, k]
            c0, c1, c2 = coeffs[n, k, 0], coeffs[n, k, 1], coeffs[n, k, 2]
            g_coeffs[n, k, 0], g_coeffs[n, k, 1], g_coeffs[n, k, 2] = b * g0, b * g1, b * g2
            g_basis[n, k] = g0 * c0 + g1 * c1 + g2 * c2
        for k in range(basis.shape[1], coeffs.shape[1]):
            g_coeffs[n, k, 0] = g_coeffs[n, k, 1] = g_coeffs[n, k, 2] = 0.0


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _Contract(torch.autograd.Function):
    """``(basis [N, K], coeffs [N, K', 3], K' >= K) -> [N, 3]``: the basis times the first K coefficients."""

    @staticmethod
    def forward(ctx, basis: Tensor, coeffs: Tensor) -> Tensor:
        b, c = _np(basis), _np(coeffs)
        out = np.empty((b.shape[0], 3), b.dtype)
        if b.shape[0]:
            run_parallel(_contract_forward, b, c, out, chunk=GAUSSIANS_PER_CHUNK)
        ctx.save_for_backward(basis, coeffs)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: Tensor):
        basis, coeffs = ctx.saved_tensors
        b, c = _np(basis), _np(coeffs)
        g_basis, g_coeffs = np.empty_like(b), np.empty_like(c)
        if b.shape[0]:
            run_parallel(_contract_backward, b, c, _np(grad.to(basis.dtype)), g_basis, g_coeffs,
                         chunk=GAUSSIANS_PER_CHUNK)
        return torch.from_numpy(g_basis), torch.from_numpy(g_coeffs)


def evaluate_sh(
    sh: Tensor,  # [N, num_sh_coeffs, 3]
    dirs: Tensor,  # [N, 3] unit view directions (camera centre -> mean)
    degree: int,
) -> Tensor:  # [N, 3]
    """Sum of the SH basis times coefficients, for bands 0..degree (no +0.5 offset, no clamp).

    The contraction is one compiled pass forward and one backward (module docstring). Written with torch ops, its
    backward costs more than the rest of a CPU fit's colour path: one coefficient at a time (``sh[:, k]``), autograd
    zero-fills a whole ``[N, K, 3]`` gradient per coefficient; as one broadcast product and sum it still makes
    several ``[N, K, 3]`` temporaries.
    """
    if degree == 0:  # the basis is one constant: no direction, no contraction
        return sh[:, 0] * sh_basis(torch.zeros(1, 3, dtype=sh.dtype, device=sh.device), 0)[0, 0]
    basis = sh_basis(dirs.to(sh.dtype), degree)  # [N, k]
    if sh.device.type != "cpu":
        k = basis.shape[1]
        return (basis.unsqueeze(-1) * sh[:, :k]).sum(1)
    return _Contract.apply(basis, sh)


def evaluate_sh_reference(sh: Tensor, dirs: Tensor, degree: int) -> Tensor:  # [N, K, 3], [N, 3] -> [N, 3]
    """``evaluate_sh`` as a plain torch sum over the coefficients (the reference of the tests)."""
    basis = sh_basis(dirs.to(sh.dtype), degree)
    out = torch.zeros(sh.shape[0], 3, dtype=sh.dtype)
    for k in range(basis.shape[1]):
        out = out + basis[:, k : k + 1] * sh[:, k]
    return out


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
    values = evaluate_sh(sh, view_dirs, degree)
    return torch.clamp_min(values + 0.5, 0.0)
