"""seggaussian.labels.placement: the similarity fit, the local registration and both shares against brute-force references,
degenerate inputs (no NaN, no crash) and the refusal's one line."""

from __future__ import annotations

import numpy as np
import pytest

from seggaussian.labels.placement import (Placement, PlacementError, check_placement, fit_similarity, local_offset,
                                   measure_placement, placement_failure, sample_surface)
from seggaussian.util.seeds import scene_seed


def _box_room() -> tuple[np.ndarray, np.ndarray]:
    """A 4 x 3 x 2.5 m room (6 walls, 2 triangles each) with a 0.8 m table-like box inside: (vertices, faces)."""
    def box(lo, hi, inward):
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                      [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)
        f = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6], [0, 4, 5], [0, 5, 1],
                      [1, 5, 6], [1, 6, 2], [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]])
        return v, (f[:, ::-1] if inward else f)

    v1, f1 = box((0, 0, 0), (4, 3, 2.5), True)
    v2, f2 = box((1.2, 0.9, 0), (2.0, 1.7, 0.75), False)
    v3, f3 = box((2.8, 2.2, 0), (3.5, 2.9, 1.8), False)
    return np.concatenate([v1, v2, v3]), np.concatenate([f1, f2 + 8, f3 + 16])


@pytest.fixture(scope="module")
def room():
    points, faces = _box_room()
    surface = sample_surface(points, faces, 30_000, 1)
    return points, faces, surface


def _rotz(deg):
    t = np.radians(deg)
    return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])


def _distances(means, surface):
    """Brute force: distance from every mean to its nearest surface sample (the reference of the KD-tree)."""
    out = np.empty(len(means))
    for i in range(0, len(means), 128):
        d = np.linalg.norm(means[i:i + 128, None, :] - surface[None, :, :], axis=2)
        out[i:i + 128] = d.min(axis=1)
    return out


def test_fit_similarity_recovers_a_known_similarity_and_stays_proper_on_a_mirror():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(200, 3))
    rot = _rotz(37.0) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])
    y = 1.7 * x @ rot.T + np.array([0.3, -2.0, 5.0])
    r, t, s = fit_similarity(x, y, np.ones(len(x)))
    np.testing.assert_allclose(r, rot, atol=1e-10)
    np.testing.assert_allclose(t, [0.3, -2.0, 5.0], atol=1e-10)
    assert s == pytest.approx(1.7, abs=1e-10)
    r, _, _ = fit_similarity(x, x * np.array([1, 1, -1.0]), np.ones(len(x)))   # a mirror: best proper rotation
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_sample_surface_is_on_the_triangles_and_uniform_by_area(room):
    points, faces, surface = room
    assert np.all(surface >= points.min(axis=0) - 1e-9) and np.all(surface <= points.max(axis=0) + 1e-9)
    floor = np.abs(surface[:, 2]) < 1e-9
    # floor area 12 m^2 less the two boxes' footprints (they sit on it; their bottoms face down, area 0.64 + 0.49)
    total = 2 * (4 * 3 + 4 * 2.5 + 3 * 2.5) + 2 * (0.64 + 0.8 * 0.75 * 2) + 2 * (0.49 + 0.7 * 1.8 * 2)
    expected_floor = (12 + 0.64 + 0.49) / total
    assert floor.mean() == pytest.approx(expected_floor, abs=0.01)


@pytest.mark.parametrize("shift,deg,scale", [((0.0, 0.0, 0.0), 0.0, 1.0), ((0.2, 0.0, 0.0), 0.0, 1.0),
                                             ((0.0, 0.0, 0.0), 6.0, 1.0), ((0.0, 0.0, 0.0), 0.0, 1.1)])
def test_local_offset_measures_the_move_back_onto_the_mesh(room, shift, deg, scale):
    points, faces, surface = room
    rng = np.random.default_rng(5)
    splat = sample_surface(points, faces, 8000, 9) + rng.normal(0, 0.005, (8000, 3))
    centre = np.array([2.0, 1.5, 1.25])
    moved = scale * (splat - centre) @ _rotz(deg).T + centre + np.array(shift)
    rms, centroid_shift, angle, dscale = local_offset(moved, np.ones(len(moved)), surface, 0.065)
    truth = float(np.sqrt(np.mean(np.sum((moved - splat) ** 2, axis=1))))
    if truth < 0.01:
        assert rms < 0.01
    else:
        assert rms == pytest.approx(truth, rel=0.25), (rms, truth)
        assert angle == pytest.approx(deg, abs=1.0) and dscale == pytest.approx(abs(scale - 1), abs=0.02)


def test_shares_match_brute_force(room):
    points, faces, surface = room
    rng = np.random.default_rng(7)
    on = sample_surface(points, faces, 3000, 11)
    off = rng.uniform([0, 0, 0], [4, 3, 2.5], size=(1000, 3))
    means = np.concatenate([on, off])
    opacity = rng.uniform(0.05, 1.0, len(means))
    dense = sample_surface(points, faces, 40_000, 13)
    distances = _distances(means, dense)
    gate = 0.065
    p = measure_placement(means, opacity, distances, gate, points, faces, "room", 0)
    within = distances <= gate
    assert p.on_mesh_share == pytest.approx(opacity[within].sum() / opacity.sum(), abs=1e-12)
    assert p.on_mesh_share_unweighted == pytest.approx(within.mean(), abs=1e-12)
    # the covered share against brute force on the same surface samples
    samples = sample_surface(points, faces, p.surface_samples, scene_seed(0, "room"))
    covered = _distances(samples, means) <= gate
    assert p.surface_covered_share == pytest.approx(covered.mean(), abs=1e-12)
    assert p.local_offset < 0.02


def test_degenerate_inputs_give_finite_figures(room):
    points, faces, _ = room
    empty = measure_placement(np.zeros((0, 3)), np.zeros(0), np.zeros(0), 0.05, points, faces, "e")
    transparent = measure_placement(np.ones((5, 3)), np.zeros(5), np.zeros(5), 0.05, points, faces, "t")
    nan = measure_placement(np.array([[np.nan, 0, 0], [1, 1, 1]]), np.ones(2), np.array([-1.0, 0.5]), 0.05,
                            points, faces, "n")
    for p in (empty, transparent, nan):
        assert all(np.isfinite(v) for v in p if isinstance(v, float)), p
        assert placement_failure(p, 0.4, 0.05, 0.07) is not None


def test_refusal_is_one_line_naming_the_figures_and_the_cause():
    bad = Placement(0.12, 0.2, 0.3, 0.065, 20000, 0.33, 1.2, 0.9, 0.5, 30.0, 0.6)
    with pytest.raises(PlacementError) as info:
        check_placement(bad, 0.4, 0.05, 0.07, "scene0")
    message = str(info.value)
    assert "\n" not in message and "scene0" in message and "12.0 %" in message and "--transform" in message
    shifted = Placement(0.6, 0.6, 0.7, 0.065, 20000, 1.0, 0.2, 0.25, 0.25, 0.1, 0.0)
    message = placement_failure(shifted, 0.4, 0.05, 0.07)
    assert "25.0 cm" in message and "--transform" in message
    assert placement_failure(shifted, 0.4, 0.05, -1.0) is None                       # negative: check off
    assert placement_failure(Placement(0.9, 0.9, 0.9, 0.065, 20000, 1, 0, 0.01, 0, 0, 0), 0.4, 0.05, 0.07) is None
