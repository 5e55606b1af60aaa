"""Binning: the radix / counting-sort path against the former argsort path and a naive binning, degenerate inputs,
and the Gaussian-major gradient slots of the blending backward against the serial sum."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from seggaussian.core.constants import TILE_SIZE
from seggaussian.render.binning_numba import bin_sorted, depth_order
from seggaussian.render.projection import Projection
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.rasterize import rasterize
from seggaussian.render.tiles import bin_gaussians, bin_gaussians_argsort
from test_render_common import camera, random_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _same_bins(a, b):
    assert (a.tiles_x, a.tiles_y) == (b.tiles_x, b.tiles_y)
    assert np.array_equal(a.offsets, b.offsets)
    assert np.array_equal(a.gaussian_ids, b.gaussian_ids)


def _projection(depths, boxes, valid=None) -> Projection:
    n = len(depths)
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    zeros = torch.zeros(n, 3, dtype=torch.float64)
    return Projection(torch.zeros(n, 2, dtype=torch.float64), zeros, torch.as_tensor(depths, dtype=torch.float64),
                      torch.from_numpy(valid), torch.as_tensor(np.asarray(boxes, np.int64).reshape(n, 4)), zeros)


@pytest.mark.parametrize("depths", [
    np.array([3.0, -0.0, 0.0, np.nan, -1.0, np.inf, -np.inf, 0.0, np.nan, -2.5, 1e-300, -1e-300, 3.0]),
    np.random.default_rng(0).integers(0, 4, 2000).astype(np.float64),  # many equal depths
    np.random.default_rng(1).normal(size=50_000),
    np.concatenate([3.0 + np.arange(3000) * 1e-15, [1e9, 0.02]]),  # a long run sharing its top key bits
    np.full(1000, 2.5),
])
def test_depth_order_is_a_stable_argsort(depths):
    idx = np.random.default_rng(2).permutation(len(depths))  # depth_order sorts any index list, ties by position
    idx.sort()
    expected = idx[np.argsort(depths[idx], kind="stable")]
    assert np.array_equal(depth_order(idx, depths), expected)


@pytest.mark.parametrize("width,height", [(100, 70), (16, 16), (1, 1), (33, 17)])
def test_bins_match_the_argsort_path(width, height):
    scene = random_scene(600, 21, dtype=torch.float64, spread=1.0)
    viewmat, K = camera(width, height)
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, width, height)
    opac = torch.sigmoid(scene["opacity_logits"])
    _same_bins(bin_gaussians(proj, width, height, opac), bin_gaussians_argsort(proj, width, height, opac))
    _same_bins(bin_gaussians(proj, width, height), bin_gaussians_argsort(proj, width, height))


def test_degenerate_binning_inputs():
    w, h = 64, 48
    # zero Gaussians; all culled
    for proj in (_projection([], np.zeros((0, 4))), _projection([1.0, 2.0], [[0, 0, 5, 5]] * 2, [False, False])):
        bins = bin_gaussians(proj, w, h)
        assert bins.num_intersections == 0 and np.array_equal(bins.offsets, np.zeros(4 * 3 + 1))
        _same_bins(bins, bin_gaussians_argsort(proj, w, h))
    # boxes exactly on tile borders (last pixel of a tile, first of the next), equal depths, one tile
    boxes = [[15, 15, 16, 16], [0, 0, 15, 15], [16, 0, 16, 0], [63, 47, 63, 47], [0, 0, 63, 47], [15, 0, 15, 47]]
    depths = [2.0, 1.0, 2.0, 1.0, 2.0, 1.0]
    proj = _projection(depths, boxes)
    bins = bin_gaussians(proj, w, h)
    _same_bins(bins, bin_gaussians_argsort(proj, w, h))
    assert bins.gaussian_ids[bins.offsets[0]:bins.offsets[1]].tolist() == [1, 5, 0, 4]  # tile (0, 0)
    assert bins.gaussian_ids[bins.offsets[5]:bins.offsets[6]].tolist() == [0, 4]  # tile (1, 1)
    one = bin_gaussians(_projection([1.0] * 3, [[0, 0, 3, 3]] * 3), 8, 8)
    assert one.offsets.tolist() == [0, 3] and one.gaussian_ids.tolist() == [0, 1, 2]


def test_inverse_numbering_lists_each_gaussians_slots():
    scene = random_scene(300, 4, dtype=torch.float64, spread=1.0)
    viewmat, K = camera(100, 70)
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, 100, 70)
    idx = np.flatnonzero(proj.valid.numpy())
    offsets, ids, order, start, rank = bin_sorted(idx, proj.depths.numpy(), proj.pixel_box.numpy(), TILE_SIZE, 7, 5)
    slots = np.empty_like(rank)
    slots[rank] = np.arange(len(rank))
    for j, g in enumerate(order):
        mine = slots[start[j]:start[j + 1]]
        assert np.all(np.diff(mine) > 0) and np.all(ids[mine] == g)
    assert start[-1] == len(ids)


@pytest.mark.parametrize("num", [0, 1, 200])
def test_grouped_backward_slots_match_the_serial_sum(num, monkeypatch):
    """The blending gradients with Gaussian-major slots equal (bit for bit) those of plain TileBins (serial sum)."""
    import sys

    from seggaussian.render.results import TileBins

    rasterize_module = sys.modules["seggaussian.render.rasterize"]  # the package exports a function of that name

    scene = random_scene(num, 8, dtype=torch.float32, spread=0.8)
    viewmat, K = camera()

    def grads(plain: bool):
        if plain:
            monkeypatch.setattr(rasterize_module, "bin_gaussians",
                                lambda *a: TileBins(*bin_gaussians(*a)))  # drops the inverse numbering
        else:
            monkeypatch.setattr(rasterize_module, "bin_gaussians", bin_gaussians)
        leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        out = rasterize(leaves["means"], leaves["quats"], leaves["log_scales"], leaves["opacity_logits"], viewmat, K,
                        64, 48, sh=leaves["sh"], backend="fast")
        (out.image.square().sum() + out.alpha.sum() + out.depth.sum()).backward()
        return [leaves[k].grad for k in ("means", "quats", "log_scales", "opacity_logits", "sh")]

    for a, b in zip(grads(True), grads(False)):
        assert a is not None and torch.equal(a, b)
    assert all(math.isfinite(float(g.abs().sum())) for g in grads(False))
