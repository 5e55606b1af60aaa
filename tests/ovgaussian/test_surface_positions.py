"""ovgaussian.model.surface: the projection that places a splat's Gaussians on its own surface, against its
point-by-point reference, on degenerate inputs, and for what it is for (a thick shell collapses, a thin surface stays,
the count of Gaussians does not matter); and that the predictor places a scene so."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ovgaussian.model.surface import SURFACE_CELL, surface_positions, surface_positions_reference


def _shell(rng, n, thickness):
    """A 1 m x 0.8 m floor patch and a wall patch meeting it, Gaussians spread ``thickness`` off them."""
    floor = np.c_[rng.uniform(0, 1.0, (n, 2)) * [1.0, 0.8], rng.normal(0, thickness, n)]
    wall = np.c_[rng.uniform(0, 1.0, n), rng.normal(0, thickness, n) + 0.8, rng.uniform(0.1, 0.9, n)]
    return np.concatenate([floor, wall])


@pytest.mark.parametrize("radius", [0.06, 0.15, 0.3])
def test_fast_projection_is_the_reference(radius):
    rng = np.random.default_rng(int(radius * 100))
    means = _shell(rng, 400, 0.03)
    opacity = rng.uniform(0, 1, len(means))
    opacity[::17] = 0.0  # Gaussians that weigh nothing still move with their cell
    np.testing.assert_allclose(surface_positions(means, opacity, radius),
                               surface_positions_reference(means, opacity, radius), atol=1e-12)


def test_cells_of_a_splat_spread_over_kilometres():
    """Two rooms 200 km apart: the cells no longer fit one int64 key each and are found row by row; the projection
    is still the reference's."""
    rng = np.random.default_rng(4)
    room = _shell(rng, 150, 0.03)
    means = np.concatenate([room, room + [2.0e5, 2.0e5, 2.0e5]])
    opacity = rng.uniform(0.1, 1, len(means))
    np.testing.assert_allclose(surface_positions(means, opacity, 0.15),
                               surface_positions_reference(means, opacity, 0.15), atol=1e-9)


@pytest.mark.parametrize("case", ["empty", "one", "same point", "no opacity", "radius 0", "line"])
def test_degenerate_inputs(case):
    rng = np.random.default_rng(0)
    means, opacity, radius = rng.normal(size=(50, 3)) * 0.05, rng.uniform(0, 1, 50), 0.15
    if case == "empty":
        means, opacity = means[:0], opacity[:0]
    elif case == "one":
        means, opacity = means[:1], opacity[:1]
    elif case == "same point":
        means = np.tile([0.3, -0.2, 1.0], (50, 1))
    elif case == "no opacity":
        opacity = np.zeros(50)
    elif case == "radius 0":
        radius = 0.0
    elif case == "line":
        means = np.c_[np.linspace(0, 0.5, 50), np.zeros(50), np.zeros(50)]
    out = surface_positions(means, opacity, radius)
    assert out.shape == means.shape and np.isfinite(out).all()
    np.testing.assert_allclose(out, surface_positions_reference(means, opacity, radius), atol=1e-12)
    np.testing.assert_allclose(out, means, atol=1e-12)  # nothing to project onto: nothing moves


def test_a_thick_shell_collapses_and_a_thin_surface_stays():
    """A fit's shell (4 cm off the surfaces, both sides) ends half a centimetre from them (median; the tail at 95 % is
    cut to under a third); Gaussians on the surfaces
    move by about their own 0.5 mm spread; hardly any slides along the surface by more than a cell."""
    rng = np.random.default_rng(1)
    n = 6000
    thick = _shell(rng, n, 0.04)
    opacity = rng.uniform(0.2, 1.0, len(thick))
    placed = surface_positions(thick, opacity, 0.15)
    off = np.r_[np.abs(placed[:n, 2]), np.abs(placed[n:, 1] - 0.8)]
    before = np.r_[np.abs(thick[:n, 2]), np.abs(thick[n:, 1] - 0.8)]
    interior = np.r_[(placed[:n, 0] > 0.2) & (placed[:n, 1] < 0.6), placed[n:, 2] > 0.2]  # away from the corner
    assert np.median(before[interior]) > 0.025 and np.median(off[interior]) < 0.005
    assert np.quantile(off[interior], 0.95) < 0.3 * np.quantile(before[interior], 0.95)
    thin = _shell(rng, n, 0.0005)
    moved = np.linalg.norm(surface_positions(thin, opacity, 0.15) - thin, axis=1)
    assert np.quantile(moved, 0.9) < 0.002  # their own 0.5 mm spread, and the corner
    tangential = np.r_[np.linalg.norm(placed[:n, :2] - thick[:n, :2], axis=1),
                       np.linalg.norm(placed[n:, [0, 2]] - thick[n:, [0, 2]], axis=1)]
    assert np.quantile(tangential[interior], 0.95) < SURFACE_CELL


def test_the_count_of_gaussians_on_a_surface_does_not_move_it():
    """Eight times as many Gaussians in the same shell (a denser fit) give the same surface: the plane is measured
    through opacity-weighted support cells, not a count of neighbours."""
    rng = np.random.default_rng(2)
    sparse = _shell(rng, 1500, 0.04)
    dense = _shell(rng, 12000, 0.04)
    for means in (sparse, dense):
        placed = surface_positions(means, np.full(len(means), 0.6), 0.15)
        half = len(means) // 2
        interior = (placed[:half, 0] > 0.2) & (placed[:half, 1] < 0.6)
        assert np.median(np.abs(placed[:half, 2][interior])) < 0.006


def test_the_predictor_places_a_scene_on_its_surface():
    """A run with ``surface_radius`` voxelizes the placed positions: the predictor's vectors are those of the network
    fed the projection directly (recentred as the predictor recentres)."""
    from ovgaussian.model.config import OVGaussianNetConfig
    from ovgaussian.model.network import OVGaussianNet, gaussian_attributes
    from ovgaussian.predict.query import ModelPredictor
    from ovgaussian.run.config import TextConfig
    from test_train import make_scene

    scene = make_scene(0)
    g = scene.gaussians
    net = OVGaussianNet(OVGaussianNetConfig.slim(embedding_width=8, surface_radius=0.15, voxel_size=0.1)).eval()
    placed = surface_positions(g.means, g.opacities(), 0.15)
    assert np.abs(placed - g.means).max() > 1e-4  # the test scene is not already flat
    centre = 0.5 * (g.means.min(axis=0) + g.means.max(axis=0))
    with torch.no_grad():
        direct = net(torch.from_numpy((placed - centre).astype(np.float32)), gaussian_attributes(g),
                     torch.zeros(len(g), dtype=torch.int64)).numpy()
    np.testing.assert_allclose(ModelPredictor(net, TextConfig()).encode_gaussians(g), direct, atol=1e-6)
