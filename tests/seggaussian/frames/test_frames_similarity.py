"""Similarity algebra and validation, and moving Gaussians: means, covariances, SH colour, reflections."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from frames_common import random_gaussians, random_rotation

from seggaussian.frames.similarity import Similarity, transform_gaussians, transform_gaussians_reference
from seggaussian.core.gaussians import Gaussians
from seggaussian.render.sh import evaluate_sh


def _sims(seed: int = 0) -> dict[str, Similarity]:
    rng = np.random.default_rng(seed)
    return {
        "rotation": Similarity(random_rotation(rng), rng.normal(size=3), 1.0),
        "scaled_rotation": Similarity(random_rotation(rng), rng.normal(size=3) * 5, 2.5),
        "reflection": Similarity(random_rotation(rng) @ np.diag([1.0, -1.0, 1.0]), rng.normal(size=3), 0.4),
        "axes_RUB": Similarity(np.diag([1.0, -1.0, -1.0]), np.zeros(3), 1.0),
        "axes_RUF": Similarity(np.diag([1.0, -1.0, 1.0]), np.array([0.5, 0.0, -2.0]), 1.0),
    }


# --- the similarity itself ------------------------------------------------------------------------


@pytest.mark.parametrize("name,sim", list(_sims().items()))
def test_matrix_round_trip_inverse_and_composition(name, sim):
    m = sim.matrix
    back = Similarity.from_matrix(m, source="test")
    np.testing.assert_allclose(back.matrix, m, atol=1e-12)
    assert back.is_reflection == (np.linalg.det(m[:3, :3]) < 0) == sim.is_reflection
    assert back.scale == pytest.approx(sim.scale, rel=1e-12)
    np.testing.assert_allclose(sim.inverse().matrix, np.linalg.inv(m), atol=1e-12)
    assert sim.compose(sim.inverse()).is_identity and sim.inverse().compose(sim).is_identity
    other = _sims(1)["scaled_rotation"]
    np.testing.assert_allclose(sim.compose(other).matrix, m @ other.matrix, atol=1e-12)
    points = np.random.default_rng(2).normal(size=(10, 3))
    np.testing.assert_allclose(sim.compose(other).apply(points), sim.apply(other.apply(points)), atol=1e-12)
    homogeneous = np.c_[points, np.ones(10)] @ m.T
    np.testing.assert_allclose(sim.apply(points), homogeneous[:, :3], atol=1e-12)


def test_identity_and_is_identity():
    assert Similarity.identity().is_identity
    assert not Similarity(np.eye(3), [0.0, 0.0, 1e-6], 1.0).is_identity
    assert not Similarity(np.eye(3), np.zeros(3), 1.0 + 1e-6).is_identity
    assert not Similarity(np.diag([1.0, 1.0, -1.0]), np.zeros(3)).is_identity


def test_matrix_rounded_to_six_digits_is_accepted_and_made_exactly_orthogonal():
    sim = _sims()["scaled_rotation"]
    rounded = np.round(sim.matrix, 6)
    back = Similarity.from_matrix(rounded)
    np.testing.assert_allclose(back.rotation @ back.rotation.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(back.matrix, sim.matrix, atol=1e-5)


@pytest.mark.parametrize("matrix,message", [
    (np.diag([1.0, 2.0, 1.0, 1.0]), "non-uniform scale"),
    (np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "shear"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.1, 1.0]]), "last row"),
    (np.diag([0.0, 0.0, 0.0, 1.0]), "singular"),
    (np.eye(3), "4x4"),
    (np.full((4, 4), np.nan), "NaN"),
    ([["a"] * 4] * 4, "numbers"),
])
def test_from_matrix_refuses_non_similarities_in_one_line_naming_the_source(matrix, message):
    with pytest.raises(ValueError, match=message) as info:
        Similarity.from_matrix(matrix, source="my.json [world_from_splat]")
    assert str(info.value).startswith("my.json [world_from_splat]: ")
    assert "\n" not in str(info.value)


def test_constructor_refuses_bad_fields():
    with pytest.raises(ValueError, match="rotation"):
        Similarity(np.diag([1.0, 2.0, 1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="scale"):
        Similarity(np.eye(3), np.zeros(3), -1.0)
    with pytest.raises(ValueError, match="translation"):
        Similarity(np.eye(3), np.zeros(2))


def test_fields_are_read_only():
    sim = Similarity(np.eye(3), np.zeros(3))
    with pytest.raises(ValueError):
        sim.rotation[0, 0] = 2.0


# --- moving Gaussians -----------------------------------------------------------------------------


def _rotations_equal(a: Gaussians, b: Gaussians, atol: float) -> None:
    np.testing.assert_allclose(a.rotation_matrices(), b.rotation_matrices(), atol=atol)


@pytest.mark.parametrize("name,sim", list(_sims().items()))
def test_means_covariances_and_kept_fields(name, sim):
    g = random_gaussians(60, 3, seed=3)
    moved = transform_gaussians(g, sim)
    np.testing.assert_allclose(moved.means, sim.apply(g.means.astype(np.float64)), rtol=1e-6, atol=1e-6)
    m = sim.scale * sim.rotation
    expected = np.einsum("ij,njk,lk->nil", m, g.covariances().astype(np.float64), m)
    np.testing.assert_allclose(moved.covariances(), expected, rtol=1e-5, atol=1e-7 * sim.scale**2)
    np.testing.assert_allclose(moved.log_scales, g.log_scales + np.log(sim.scale), atol=1e-6)
    np.testing.assert_array_equal(moved.opacity_logits, g.opacity_logits)
    assert moved.extras.keys() == g.extras.keys()
    np.testing.assert_array_equal(moved.extras["semantic"], g.extras["semantic"])
    for name_ in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert getattr(moved, name_).dtype == np.float32
    # a proper rotation for every Gaussian, even under a reflection
    assert np.allclose(np.linalg.det(moved.rotation_matrices()), 1.0, atol=1e-5)


@pytest.mark.parametrize("name,sim", list(_sims(4).items()))
def test_view_dependent_colour_follows_the_transform(name, sim):
    """colour'(M d) == colour(d) for every Gaussian and direction: the renderer's evaluate_sh is the judge."""
    g = random_gaussians(80, 3, seed=5)
    moved = transform_gaussians(g, sim)
    rng = np.random.default_rng(6)
    dirs = rng.normal(size=(80, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    before = evaluate_sh(torch.from_numpy(g.sh.astype(np.float64)), torch.from_numpy(dirs), 3)
    after = evaluate_sh(torch.from_numpy(moved.sh.astype(np.float64)), torch.from_numpy(dirs @ sim.rotation.T), 3)
    np.testing.assert_allclose(after.numpy(), before.numpy(), atol=2e-6)


@pytest.mark.parametrize("name,sim", list(_sims(7).items()))
def test_fast_transform_equals_reference(name, sim):
    g = random_gaussians(40, 3, seed=8)
    fast, slow = transform_gaussians(g, sim), transform_gaussians_reference(g, sim)
    np.testing.assert_allclose(fast.means, slow.means, atol=1e-6)
    _rotations_equal(fast, slow, atol=1e-6)
    np.testing.assert_allclose(fast.log_scales, slow.log_scales, atol=1e-6)
    np.testing.assert_allclose(fast.sh, slow.sh, atol=2e-6)


def test_identity_is_a_no_op():
    g = random_gaussians(30, 3, seed=9)
    moved = transform_gaussians(g, Similarity.identity())
    np.testing.assert_array_equal(moved.means, g.means)
    np.testing.assert_array_equal(moved.log_scales, g.log_scales)
    np.testing.assert_allclose(moved.sh, g.sh, atol=1e-7)
    _rotations_equal(moved, g, atol=1e-7)


def test_transforms_compose():
    g = random_gaussians(30, 2, seed=10)
    a, b = _sims(11)["reflection"], _sims(12)["scaled_rotation"]
    twice = transform_gaussians(transform_gaussians(g, a), b)
    once = transform_gaussians(g, b.compose(a))
    np.testing.assert_allclose(twice.means, once.means, atol=2e-5)
    _rotations_equal(twice, once, atol=1e-6)
    np.testing.assert_allclose(twice.log_scales, once.log_scales, atol=1e-6)
    np.testing.assert_allclose(twice.sh, once.sh, atol=2e-6)


def test_reflection_back_and_forth_restores_the_gaussians():
    g = random_gaussians(30, 3, seed=13)
    sim = _sims(14)["reflection"]
    back = transform_gaussians(transform_gaussians(g, sim), sim.inverse())
    np.testing.assert_allclose(back.means, g.means, atol=1e-5)
    np.testing.assert_allclose(back.covariances(), g.covariances(), atol=1e-6)
    np.testing.assert_allclose(back.sh, g.sh, atol=2e-6)


def test_zero_quaternion_is_read_as_identity_and_moved_by_the_rotation():
    g = random_gaussians(3, 0, seed=15)
    g = Gaussians(g.means, np.zeros_like(g.quats), g.log_scales, g.opacity_logits, g.sh)
    sim = _sims(16)["reflection"]
    moved = transform_gaussians(g, sim)
    np.testing.assert_allclose(moved.rotation_matrices(), np.repeat(sim.proper_rotation[None], 3, 0), atol=1e-6)
    np.testing.assert_array_equal(moved.sh, g.sh)


def test_empty_gaussians_and_wrong_argument_types():
    empty = Gaussians.empty(sh_degree=3)
    assert len(transform_gaussians(empty, _sims()["reflection"])) == 0
    assert len(transform_gaussians_reference(empty, _sims()["reflection"])) == 0
    with pytest.raises(TypeError, match="Similarity"):
        transform_gaussians(empty, np.eye(4))
