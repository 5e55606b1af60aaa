"""Rotation (and reflection) of real spherical-harmonic colour coefficients in the 3DGS basis.

The basis is the one ``seggaussian.render.sh.evaluate_sh`` evaluates, signs included: band 1 is
``(-C1 y, C1 z, -C1 x)``, bands 2 and 3 carry the signed constants ``SH_C2``, ``SH_C3`` of
``seggaussian.core.constants``. ``basis_columns`` below is the one copy of those polynomials; ``sh_basis`` evaluates
them in numpy, ``seggaussian.render.sh.sh_basis`` in torch.

For an orthogonal ``M`` (a rotation, or a reflection with det -1) each band ``l`` is mapped onto itself:
``Y_l(M d) = D_l(M) Y_l(d)`` for every unit direction ``d``, with ``D_l(M)`` orthogonal (the basis is orthonormal up
to one constant per band). A Gaussian whose colour is ``sum_m c_m Y_m(d)`` shows the same colours in the moved
frame, ``sum_m c'_m Y_m(M d) == sum_m c_m Y_m(d)``, when ``c'_l = D_l(M) c_l``. For a reflection ``M = -Q``
(``Q`` a rotation) ``D_l(M) = (-1)^l D_l(Q)``: a band-``l`` harmonic has parity ``(-1)^l``.

Fast path: ``D_l`` from an exact linear solve on a fixed, well-conditioned set of directions (the pseudo-inverse
of the basis on those directions is computed once per band). Reference: ``rotate_sh_reference`` fits the new
coefficients by least squares on many random directions, straight from the defining equation above.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from seggaussian.core.constants import MAX_SH_DEGREE, SH_C0, SH_C1, SH_C2, SH_C3

#: A matrix counts as orthogonal when ``max |M^T M - I| <= ROTATION_TOL``: float32 matrices carry ~1e-7 of
#: rounding and matrices printed with 6-7 digits ~1e-6; a real shear or non-uniform scale is far beyond this.
ROTATION_TOL = 1e-5
#: The fast path solves for ``D_l`` on this many fixed directions (a Fibonacci sphere): with 20 the basis
#: matrices of bands 1..3 have condition numbers below 1.5, so the solve loses no precision.
FIXED_DIRECTION_COUNT = 20
#: The reference fits on this many random directions (any number well above 16 = (3 + 1)^2 works).
REFERENCE_DIRECTION_COUNT = 256
#: Seed of the reference's random directions (the reference is deterministic).
REFERENCE_SEED = 20240611


def num_coeffs(degree: int) -> int:
    """``(degree + 1)^2`` coefficients per channel."""
    return (degree + 1) ** 2


def band_slice(band: int) -> slice:
    """The coefficients of band ``l``: indices ``l^2 .. (l+1)^2 - 1``."""
    return slice(band * band, (band + 1) ** 2)


def _check_degree(degree: int) -> int:
    degree = int(degree)
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return degree


def _degree_of_coeffs(k: int) -> int:
    degree = int(round(np.sqrt(k))) - 1
    if degree < 0 or num_coeffs(degree) != k or degree > MAX_SH_DEGREE:
        raise ValueError(f"sh has {k} coefficients per channel, expected (d+1)^2 for d in 0..{MAX_SH_DEGREE}")
    return degree


def check_orthogonal(rotation, name: str = "rotation") -> np.ndarray:
    """``rotation`` as a float64 ``[3, 3]`` array; ValueError (one line, naming ``name``) unless orthogonal."""
    m = np.asarray(rotation, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"{name}: expected a 3x3 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError(f"{name}: holds NaN/Inf")
    error = float(np.abs(m.T @ m - np.eye(3)).max())
    if error > ROTATION_TOL:
        raise ValueError(f"{name}: not orthogonal (max |M^T M - I| = {error:.3g} > {ROTATION_TOL})")
    return m


def basis_columns(x, y, z, ones, degree: int) -> list:
    """The ``(degree + 1)^2`` basis functions at the direction components ``x, y, z`` (numpy arrays or torch tensors
    of one shape; ``ones`` of that shape too), in coefficient order: the one copy of the 3DGS polynomials, constants
    and signs, shared by ``sh_basis`` here (numpy) and ``seggaussian.render.sh.sh_basis`` (torch, differentiable)."""
    columns = [SH_C0 * ones]
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
    return columns


def sh_basis(dirs, degree: int) -> np.ndarray:
    """``[P, (degree+1)^2]`` float64: the 3DGS real SH basis at unit directions ``dirs`` ``[P, 3]``.

    Column ``k`` is the function that multiplies coefficient ``sh[:, k]`` in ``evaluate_sh`` (``basis_columns``)."""
    degree = _check_degree(degree)
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack(basis_columns(x, y, z, np.ones_like(x), degree), axis=1)


def fibonacci_directions(count: int) -> np.ndarray:
    """``[count, 3]`` unit directions spread over the sphere (golden-angle spiral)."""
    i = np.arange(count, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(1.0 - z * z)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@lru_cache(maxsize=None)
def _band_pinv(band: int) -> tuple[np.ndarray, np.ndarray]:
    """(fixed directions ``[F, 3]``, pseudo-inverse of band ``l`` of the basis on them ``[2l+1, F]``), read-only."""
    dirs = fibonacci_directions(FIXED_DIRECTION_COUNT)
    pinv = np.linalg.pinv(sh_basis(dirs, band)[:, band_slice(band)])
    dirs.flags.writeable = False
    pinv.flags.writeable = False
    return dirs, pinv


def band_rotation(rotation, band: int) -> np.ndarray:
    """``[2l+1, 2l+1]`` float64 ``D_l(M)`` with ``Y_l(M d) = D_l(M) Y_l(d)``, for an orthogonal ``M`` (fast path).

    Exact: ``B(M P) = B(P) D^T`` holds on the fixed directions ``P`` (the band is closed under ``O(3)``) and ``B(P)``
    has full column rank, so ``D^T = pinv(B(P)) B(M P)``."""
    m = check_orthogonal(rotation)
    band = _check_degree(band)
    if band == 0:
        return np.ones((1, 1))
    dirs, pinv = _band_pinv(band)
    moved = sh_basis(dirs @ m.T, band)[:, band_slice(band)]
    return (pinv @ moved).T


def band_rotation_reference(rotation, band: int, num_directions: int = REFERENCE_DIRECTION_COUNT) -> np.ndarray:
    """``D_l(M)`` by least squares on random directions: ``B_l(M d) X = B_l(d)`` gives ``X = D^-T = D``."""
    m = check_orthogonal(rotation)
    band = _check_degree(band)
    dirs = _random_directions(num_directions)
    before = sh_basis(dirs, band)[:, band_slice(band)]
    after = sh_basis(dirs @ m.T, band)[:, band_slice(band)]
    return np.linalg.lstsq(after, before, rcond=None)[0]


def sh_rotation_matrix(rotation, degree: int) -> np.ndarray:
    """``[K, K]`` float64 block-diagonal matrix of ``D_0 = 1, D_1 .. D_degree`` (fast path): ``c' = matrix @ c``."""
    degree = _check_degree(degree)
    k = num_coeffs(degree)
    out = np.zeros((k, k))
    out[0, 0] = 1.0
    for band in range(1, degree + 1):
        s = band_slice(band)
        out[s, s] = band_rotation(rotation, band)
    return out


def rotate_sh(sh: np.ndarray, rotation) -> np.ndarray:
    """SH coefficients ``[N, K, 3]`` of Gaussians moved by the orthogonal ``rotation`` (rotation or reflection).

    One ``[K, K]`` block-diagonal matmul, computed in float64 and returned in ``sh``'s dtype. Degree 0 is returned
    unchanged (a copy). ``colour(sh', rotation @ d) == colour(sh, d)`` for every direction ``d``."""
    sh = np.asarray(sh)
    if sh.ndim != 3 or sh.shape[2] != 3:
        raise ValueError(f"rotate_sh: sh has shape {sh.shape}, expected (N, num_sh_coeffs, 3)")
    degree = _degree_of_coeffs(sh.shape[1])
    m = check_orthogonal(rotation)
    out_dtype = sh.dtype if sh.dtype in (np.float32, np.float64) else np.float64
    if degree == 0:
        return sh.astype(out_dtype, copy=True)
    return apply_sh_matrix(sh_rotation_matrix(m, degree), sh).astype(out_dtype)


def apply_sh_matrix(matrix: np.ndarray, sh: np.ndarray) -> np.ndarray:
    """``c'_n = matrix @ c_n`` for every Gaussian ``n`` (``[K, K]`` times ``[N, K, 3]``, broadcast), float64 out.

    ``np.matmul`` broadcasting the one matrix over the Gaussians: no transposed copies (a 200k-Gaussian SH-3
    splat takes a quarter of the time of a single ``[K, K] x [K, 3N]`` product after the transposes)."""
    return np.matmul(np.asarray(matrix, dtype=np.float64), np.asarray(sh, dtype=np.float64))


def rotate_sh_reference(sh: np.ndarray, rotation, num_directions: int = REFERENCE_DIRECTION_COUNT) -> np.ndarray:
    """Slow, obvious ``rotate_sh``: the coefficients ``c'`` that best satisfy ``sum c'_m Y_m(M d) = sum c_m Y_m(d)``
    on random directions ``d`` (least squares over all bands at once; no block structure assumed), float64."""
    sh = np.asarray(sh, dtype=np.float64)
    if sh.ndim != 3 or sh.shape[2] != 3:
        raise ValueError(f"rotate_sh_reference: sh has shape {sh.shape}, expected (N, num_sh_coeffs, 3)")
    degree = _degree_of_coeffs(sh.shape[1])
    m = check_orthogonal(rotation)
    dirs = _random_directions(num_directions)
    n, k, _ = sh.shape
    colours = sh_basis(dirs, degree) @ sh.transpose(1, 0, 2).reshape(k, n * 3)  # [P, N*3]
    fitted = np.linalg.lstsq(sh_basis(dirs @ m.T, degree), colours, rcond=None)[0]  # [K, N*3]
    return fitted.reshape(k, n, 3).transpose(1, 0, 2)


def _random_directions(count: int) -> np.ndarray:
    d = np.random.default_rng(REFERENCE_SEED).normal(size=(int(count), 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)
