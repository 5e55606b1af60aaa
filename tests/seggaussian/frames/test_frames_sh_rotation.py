"""Real-SH rotation of the 3DGS basis: fast path vs least-squares reference, group properties, reflections,
and the defining property against the renderer's own ``evaluate_sh``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from frames_common import random_rotation

from seggaussian.core.constants import SH_C1
from seggaussian.frames.sh_rotation import (
    band_rotation,
    band_rotation_reference,
    rotate_sh,
    rotate_sh_reference,
    sh_basis,
    sh_rotation_matrix,
)
from seggaussian.render.sh import evaluate_sh

BANDS = (1, 2, 3)


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _matrices(seed: int = 0):
    """Rotations, reflections (det -1) and the identity."""
    rng = np.random.default_rng(seed)
    rotations = [random_rotation(rng) for _ in range(3)]
    mirror_z = np.diag([1.0, 1.0, -1.0])
    return {"identity": np.eye(3), **{f"rotation{i}": r for i, r in enumerate(rotations)},
            "inversion": -rotations[0], "mirror_z": mirror_z, "mirror_then_rotate": rotations[1] @ mirror_z,
            "swap_xy": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])}


def _evaluate(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """The renderer's SH evaluation (torch, float64), all bands."""
    degree = int(np.sqrt(sh.shape[1])) - 1
    return evaluate_sh(torch.from_numpy(np.asarray(sh, np.float64)), torch.from_numpy(dirs), degree).numpy()


def test_numpy_basis_is_the_renderers_basis():
    rng = np.random.default_rng(1)
    dirs = _unit(rng, 50)
    sh = rng.normal(size=(50, 16, 3))
    mine = np.einsum("nk,nkc->nc", sh_basis(dirs, 3), sh)
    np.testing.assert_allclose(mine, _evaluate(sh, dirs), atol=1e-13)


@pytest.mark.parametrize("name,matrix", list(_matrices().items()))
@pytest.mark.parametrize("band", BANDS)
def test_fast_band_matrix_equals_least_squares_reference(name, matrix, band):
    fast = band_rotation(matrix, band)
    reference = band_rotation_reference(matrix, band)
    np.testing.assert_allclose(fast, reference, atol=1e-12)
    assert fast.shape == (2 * band + 1, 2 * band + 1)


@pytest.mark.parametrize("name,matrix", list(_matrices().items()))
@pytest.mark.parametrize("band", BANDS)
def test_band_matrices_are_orthogonal_with_the_right_determinant(name, matrix, band):
    d = band_rotation(matrix, band)
    np.testing.assert_allclose(d @ d.T, np.eye(2 * band + 1), atol=1e-12)
    # SO(3) acts with det +1; an improper matrix M = -Q acts as (-1)^l D(Q), det (-1)^(l (2l+1)) = (-1)^l
    expected = 1.0 if np.linalg.det(matrix) > 0 else (-1.0) ** band
    assert np.linalg.det(d) == pytest.approx(expected, abs=1e-12)


def test_identity_gives_identity_blocks_and_unchanged_coefficients():
    np.testing.assert_allclose(sh_rotation_matrix(np.eye(3), 3), np.eye(16), atol=1e-13)
    sh = np.random.default_rng(2).normal(size=(7, 16, 3))
    np.testing.assert_allclose(rotate_sh(sh, np.eye(3)), sh, atol=1e-13)


def test_band_one_is_the_signed_permutation_of_the_rotation():
    """Independent closed form: band 1 is C1 P d with P = [-y; z; -x], so D1(M) = P M P^T."""
    p = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    rng = np.random.default_rng(3)
    dirs = _unit(rng, 5)
    np.testing.assert_allclose(sh_basis(dirs, 1)[:, 1:], SH_C1 * dirs @ p.T, atol=1e-15)
    for matrix in _matrices(3).values():
        np.testing.assert_allclose(band_rotation(matrix, 1), p @ matrix @ p.T, atol=1e-12)


@pytest.mark.parametrize("band", BANDS)
def test_composition_is_the_product_of_band_matrices(band):
    rng = np.random.default_rng(4)
    for _ in range(3):
        a, b = random_rotation(rng), random_rotation(rng) @ np.diag([1.0, -1.0, 1.0])
        np.testing.assert_allclose(band_rotation(a @ b, band), band_rotation(a, band) @ band_rotation(b, band),
                                   atol=1e-12)


@pytest.mark.parametrize("band", BANDS)
def test_reflection_is_rotation_times_parity(band):
    q = random_rotation(np.random.default_rng(5))
    np.testing.assert_allclose(band_rotation(-q, band), (-1.0) ** band * band_rotation(q, band), atol=1e-12)


@pytest.mark.parametrize("name,matrix", list(_matrices(6).items()))
def test_rotated_coefficients_give_the_same_colour_along_rotated_directions(name, matrix):
    """The defining property, checked with the renderer's evaluate_sh (torch): SH'(M d) == SH(d)."""
    rng = np.random.default_rng(7)
    sh = rng.normal(size=(200, 16, 3))
    dirs = _unit(rng, 200)
    rotated = rotate_sh(sh, matrix)
    np.testing.assert_allclose(_evaluate(rotated, dirs @ matrix.T), _evaluate(sh, dirs), atol=1e-12)
    # and band by band (each band is mapped onto itself)
    for band in BANDS:
        keep = np.zeros(16, bool)
        keep[band * band:(band + 1) ** 2] = True
        np.testing.assert_allclose(_evaluate(rotated * keep[None, :, None], dirs @ matrix.T),
                                   _evaluate(sh * keep[None, :, None], dirs), atol=1e-12)


@pytest.mark.parametrize("degree", (0, 1, 2, 3))
def test_fast_rotate_sh_equals_reference_for_every_degree(degree):
    rng = np.random.default_rng(8)
    sh = rng.normal(size=(20, (degree + 1) ** 2, 3))
    for matrix in _matrices(9).values():
        np.testing.assert_allclose(rotate_sh(sh, matrix), rotate_sh_reference(sh, matrix), atol=1e-12)


def test_lower_degrees_are_the_leading_blocks_of_degree_three():
    r = random_rotation(np.random.default_rng(10))
    full = sh_rotation_matrix(r, 3)
    for degree in (0, 1, 2):
        k = (degree + 1) ** 2
        np.testing.assert_array_equal(sh_rotation_matrix(r, degree), full[:k, :k])


def test_float32_input_is_computed_in_float64_and_returned_float32():
    rng = np.random.default_rng(11)
    sh64 = rng.normal(size=(30, 16, 3))
    sh32 = sh64.astype(np.float32)
    r = random_rotation(rng)
    out = rotate_sh(sh32, r)
    assert out.dtype == np.float32
    # the float32 result is the float64 rotation of the float32 input, rounded once
    exact = rotate_sh_reference(sh32.astype(np.float64), r)
    np.testing.assert_allclose(out, exact, rtol=0, atol=4 * np.finfo(np.float32).eps * np.abs(exact).max())
    # a float32 rotation matrix (orthogonal to ~1e-7) is accepted
    assert rotate_sh(sh32, r.astype(np.float32)).dtype == np.float32


def test_degree_zero_is_a_copy():
    sh = np.random.default_rng(12).normal(size=(4, 1, 3)).astype(np.float32)
    out = rotate_sh(sh, random_rotation(np.random.default_rng(13)))
    np.testing.assert_array_equal(out, sh)
    assert out is not sh and out.dtype == np.float32


@pytest.mark.parametrize("rotation,message", [
    (np.diag([1.0, 2.0, 1.0]), "not orthogonal"),
    (np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "not orthogonal"),
    (np.eye(4), "3x3"),
    (np.full((3, 3), np.nan), "NaN"),
])
def test_non_orthogonal_matrices_are_refused(rotation, message):
    with pytest.raises(ValueError, match=message) as info:
        rotate_sh(np.zeros((2, 16, 3)), rotation)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("shape", [(2, 5, 3), (2, 16), (2, 25, 3), (2, 16, 4)])
def test_bad_sh_shapes_are_refused(shape):
    with pytest.raises(ValueError, match="sh"):
        rotate_sh(np.zeros(shape), np.eye(3))
