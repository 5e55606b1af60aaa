import numpy as np
import pytest

from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.core.constants import SH_C0
from seggaussian.core.gaussians import Gaussians, sh_degree_from_coeffs
from seggaussian.core.rotations import quats_to_rotmats


def random_gaussians(n, degree=1, seed=0):
    rng = np.random.default_rng(seed)
    return Gaussians.from_arrays(
        rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 3)) - 2,
        rng.normal(size=n), rng.normal(size=(n, (degree + 1) ** 2, 3)),
    )


def test_shapes_checked_at_construction():
    g = random_gaussians(5)
    with pytest.raises(ValueError, match="quats"):
        Gaussians(g.means, g.quats[:, :3].copy(), g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(TypeError, match="float32"):
        Gaussians(g.means.astype(np.float64), g.quats, g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(ValueError, match="SH coefficients"):
        Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.zeros((5, 7, 3), np.float32))
    with pytest.raises(ValueError, match="extras"):
        g.with_extras(semantic=np.zeros(4, np.int32))


def test_derived_values():
    g = random_gaussians(50, degree=2)
    assert g.sh_degree == 2
    q = g.normalized_quats()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    r = g.rotation_matrices()
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-5)
    cov = g.covariances()
    np.testing.assert_allclose(np.linalg.eigvalsh(cov.astype(np.float64)).sum(1), (g.scales() ** 2).sum(1), rtol=1e-4)
    np.testing.assert_allclose(g.dc_colors(), 0.5 + SH_C0 * g.sh[:, 0], rtol=1e-6)
    o = Gaussians.from_arrays(g.means[:3], g.quats[:3], g.log_scales[:3], [-100.0, 0.0, 100.0], g.sh[:3]).opacities()
    assert np.isfinite(o).all() and o[0] == 0.0 and o[1] == 0.5 and o[2] == 1.0


def test_zero_quaternion_is_identity_not_nan():
    g = random_gaussians(2)
    g.quats[0] = 0.0
    q = g.normalized_quats()
    np.testing.assert_array_equal(q[0], [1, 0, 0, 0])
    assert np.isfinite(g.rotation_matrices()).all()


def test_rotmat_matches_axis_angle():
    angle = 0.7
    q = np.array([[np.cos(angle / 2), 0, 0, np.sin(angle / 2)]])
    r = quats_to_rotmats(q)[0]
    expected = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    np.testing.assert_allclose(r, expected, atol=1e-12)


def test_sh_degree_from_coeffs():
    assert [sh_degree_from_coeffs(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    for bad in (0, 2, 5, 25):
        with pytest.raises(ValueError):
            sh_degree_from_coeffs(bad)


def test_subset_keeps_extras_aligned():
    g = random_gaussians(10).with_extras(semantic=np.arange(10, dtype=np.int32))
    s = g.subset(np.array([3, 7]))
    assert len(s) == 2 and s.extras["semantic"].tolist() == [3, 7]
    np.testing.assert_array_equal(s.means, g.means[[3, 7]])


def test_camera_projection_and_look_at():
    cam = Camera(intrinsics(100, 100, 50, 40), look_at([0, -3, 1], [0, 0, 1]), 100, 80)
    uv, z = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(uv[0], [50, 40], atol=1e-9)
    np.testing.assert_allclose(z[0], 3.0)
    assert uv[1, 1] < 40  # world up (z) is image up (smaller v)
    np.testing.assert_allclose(cam.center, [0, -3, 1], atol=1e-12)
    moved = cam.translated(np.array([1e5, 0, 0]))
    uv2, _ = moved.project(np.array([[1e5, 0.0, 1.0]]))
    np.testing.assert_allclose(uv2[0], [50, 40], atol=1e-6)
    with pytest.raises(ValueError, match="NaN"):
        Camera(np.full((3, 3), np.nan), np.eye(4), 10, 10)
