"""Binning: the radix / counting-sort path against the former argsort path and a naive binning, degenerate inputs,
identical results for any thread count."""

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
    # keys spanning all 64 bits with many positions: key bits below the packed ones are ordered by the run fix-up
    np.random.default_rng(3).normal(size=100_000) * 10.0 ** np.random.default_rng(4).integers(-300, 300, 100_000),
    np.repeat(np.random.default_rng(5).normal(size=300) * 1e200, 200),  # long runs of equal wide-range keys
    # short runs of keys that differ only in their last bits (dropped from the packed word): the full key decides
    np.random.default_rng(6).permutation(np.repeat(np.random.default_rng(7).normal(size=3000) * 1e100, 5)
                                         * (1.0 + np.random.default_rng(8).integers(0, 4, 15_000) * 2.0 ** -52)),
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
    _same_bins(bin_gaussians(proj, width, height, opac, ellipse_cull=False),
               bin_gaussians_argsort(proj, width, height, opac))
    _same_bins(bin_gaussians(proj, width, height, ellipse_cull=False), bin_gaussians_argsort(proj, width, height))


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


def test_bin_sorted_returns_the_depth_order():
    scene = random_scene(300, 4, dtype=torch.float64, spread=1.0)
    viewmat, K = camera(100, 70)
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, 100, 70)
    idx = np.flatnonzero(proj.valid.numpy())
    offsets, ids, order = bin_sorted(idx, proj.depths.numpy(), proj.pixel_box.numpy(), TILE_SIZE, 7, 5)
    assert np.array_equal(order, depth_order(idx, proj.depths.numpy()))
    assert offsets[-1] == len(ids) and set(ids.tolist()) <= set(idx.tolist())


def test_binning_is_identical_for_one_and_two_threads():
    import numba

    scene = random_scene(3000, 5, dtype=torch.float32, spread=1.0)
    viewmat, K = camera(100, 70)
    threads = numba.get_num_threads()
    results = []
    for n in (1, max(2, threads)):
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
        try:
            proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, 100, 70)
            results.append((proj, bin_gaussians(proj, 100, 70, torch.sigmoid(scene["opacity_logits"]))))
        finally:
            numba.set_num_threads(threads)
    (p1, b1), (p2, b2) = results
    for a, b in zip(p1, p2):
        assert torch.equal(a, b)
    _same_bins(b1, b2)


@pytest.mark.parametrize("num", [0, 1])
def test_live_slot_backward_on_degenerate_scenes_matches_the_reference(num):
    """No Gaussian (no slot at all) and one Gaussian: the live-slot backward gives the reference's gradients."""
    from test_render_rasterize import assert_grads_close, render_with_grads

    scene = random_scene(num, 12, dtype=torch.float64, spread=0.3)
    fast, fast_grads = render_with_grads(scene, "fast")
    ref, ref_grads = render_with_grads(scene, "reference")
    assert float((fast.image - ref.image).detach().abs().max()) <= 1e-4
    assert (float(ref.alpha.max()) > 0.05) == (num > 0)  # the one Gaussian is seen
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert fast_grads[name].shape == ref_grads[name].shape == (num, *scene[name].shape[1:])
        if num:
            assert_grads_close(fast_grads[name], ref_grads[name], name)


def test_backward_stores_only_the_live_intersections():
    """A dense opaque scene stops most pixels early: the backward keeps gradient slots for the intersections some
    pixel reached only, and its gradients still match the per-pixel reference."""
    import seggaussian.render.rasterize_numba as rn
    from test_render_rasterize import assert_grads_close, render_with_grads

    scene = random_scene(400, 9, dtype=torch.float64, spread=0.6)
    scene["opacity_logits"] = scene["opacity_logits"].abs() + 3.0
    scene["log_scales"] = scene["log_scales"] + 1.5
    viewmat, K = camera()
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, 32, 24)
    bins = bin_gaussians(proj, 32, 24, torch.sigmoid(scene["opacity_logits"]))
    fast, fast_grads = render_with_grads(scene, "fast")
    ref, ref_grads = render_with_grads(scene, "reference")
    assert float((fast.image - ref.image).detach().abs().max()) <= 1e-4
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert_grads_close(fast_grads[name], ref_grads[name], name)
    # every pixel of every tile stops early, so most of each tile's list is never reached
    m2, cn, op = (rn._as_np(x) for x in (proj.means2d, proj.conics, torch.sigmoid(scene["opacity_logits"])))
    col = np.zeros((len(op), 1), np.float32)
    accum, trans = np.zeros((24, 32, 1), np.float32), np.ones((24, 32), np.float32)
    stop_pos = np.zeros((24, 32), np.int32)
    rn._forward_kernel(m2, cn, op, col, bins.rows, bins.offsets, bins.gaussian_ids, bins.tiles_x, 32, 24, accum, trans,
                       stop_pos)
    live = rn._live_slots(bins.offsets, stop_pos, bins.tiles_x, 32, 24)
    assert 0 < live[-1] < bins.num_intersections / 4


_THREADS_SCRIPT = """
import hashlib, sys
import numpy as np, torch
sys.path.insert(0, {tests!r})
from test_render_common import camera, random_scene
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.rasterize import rasterize
from seggaussian.render.tiles import bin_gaussians
scene = random_scene(20000, 11, spread=1.0)
viewmat, K = camera(160, 120)
h = hashlib.sha256()
proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, 160, 120)
bins = bin_gaussians(proj, 160, 120, torch.sigmoid(scene["opacity_logits"]))
for a in (*proj, bins.offsets, bins.gaussian_ids):
    h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
leaves = {{k: v.clone().requires_grad_(True) for k, v in scene.items()}}
out = rasterize(leaves["means"], leaves["quats"], leaves["log_scales"], leaves["opacity_logits"], viewmat, K, 160, 120,
                sh=leaves["sh"], backend="fast")
(out.image.square().sum() + out.alpha.sum() + out.depth.sum()).backward()
for a in (out.image, out.alpha, out.depth, *(leaves[k].grad for k in ("means", "quats", "log_scales", "opacity_logits", "sh"))):
    h.update(a.detach().numpy().tobytes())
print(bins.num_intersections, h.hexdigest())
"""


def test_projection_binning_and_gradients_identical_for_1_and_2_numba_threads():
    """Fresh processes with NUMBA_NUM_THREADS=1 and 2: projection, tile lists, image and gradients bit for bit."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    tests = str(Path(__file__).resolve().parent)
    script = _THREADS_SCRIPT.format(tests=tests)
    digests = []
    for threads in ("1", "2"):
        env = dict(os.environ, NUMBA_NUM_THREADS=threads, OMP_NUM_THREADS="1")
        res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
        assert res.returncode == 0, res.stderr[-2000:]
        digests.append(res.stdout.strip().splitlines()[-1])
    assert int(digests[0].split()[0]) > 0
    assert digests[0] == digests[1]


@pytest.mark.parametrize("seed, scale_shift", [(21, -1.5), (22, 0.0), (23, 1.0)])
def test_skipping_the_rows_outside_a_box_changes_nothing(seed, scale_shift):
    """The kernels skip a tile's rows outside each Gaussian's pixel box (``TileBins.rows``). With every box widened to
    the whole image no row is skipped: the forward must give the same bits, the blend weights too, and the backward
    the same gradients up to float32 summation order. Small, mid-sized and large Gaussians (boxes within one tile
    row band, across tile edges, and over whole tiles)."""
    import seggaussian.render.rasterize_numba as rn

    w, h = 70, 45  # tiles cut by the image edge on both axes
    scene = random_scene(600, seed, spread=1.0)
    scene["log_scales"] = scene["log_scales"] + scale_shift
    viewmat, K = camera(w, h)
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, w, h)
    opacities = torch.sigmoid(scene["opacity_logits"])
    bins = bin_gaussians(proj, w, h, opacities)
    whole = bins._replace(rows=np.tile(np.array([[0, h - 1]], np.int32), (len(bins.rows), 1)))
    assert (bins.rows[:, 1] - bins.rows[:, 0] < h - 1).any()  # some boxes do skip rows
    colors = torch.rand(len(opacities), 4, generator=torch.Generator().manual_seed(seed))
    results = []
    for b in (bins, whole):
        leaves = [x.detach().clone().requires_grad_(True) for x in (proj.means2d, proj.conics, opacities, colors)]
        accum, alpha = rn.blend_fast(*leaves, b)
        (accum.square().sum() + alpha.sum()).backward()
        weights = rn.blend_weights_fast(proj.means2d, proj.conics, opacities, b, 8)
        results.append((accum.detach(), alpha.detach(), weights, [x.grad for x in leaves]))
    (acc_a, alpha_a, w_a, g_a), (acc_b, alpha_b, w_b, g_b) = results
    assert torch.equal(acc_a, acc_b) and torch.equal(alpha_a, alpha_b)
    assert all(torch.equal(x, y) for x, y in zip(w_a, w_b))
    for x, y in zip(g_a, g_b):
        assert torch.allclose(x, y, rtol=1e-4, atol=1e-5 * float(y.abs().max()))

