"""Ellipse culling of tile boxes: every tile where a Gaussian can blend is kept (checked pixel by pixel against
``tiles_reached_reference``), tile lists stay in depth order, and images, blend weights and gradients equal those of
whole boxes, on needles, faint and huge Gaussians, image edges and empty ellipses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seggaussian.core.constants import ALPHA_MIN, TILE_SIZE
from seggaussian.render.binning_numba import MAX_TILES_PER_SIDE, bin_sorted
from seggaussian.render.ellipse_cull import tiles_reached_reference
from seggaussian.render.projection import Projection
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.rasterize_numba import blend_fast, blend_weights_fast
from seggaussian.render.tiles import _selected, bin_gaussians
from test_render_common import camera, random_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _scene(kind: str, seed: int):
    """Scenes whose boxes the cull trims: ``needles`` (one long axis), ``faint`` (opacities down to ALPHA_MIN),
    ``mixed`` (small to image-sized Gaussians, some centres off screen)."""
    scene = random_scene(700, seed, spread=1.0)
    g = torch.Generator().manual_seed(seed + 100)
    if kind == "needles":
        scene["log_scales"] = scene["log_scales"] + torch.tensor([1.8, -1.0, -1.0])
    elif kind == "faint":
        o = ALPHA_MIN * torch.exp(torch.rand(700, generator=g) * 5.0)  # ALPHA_MIN .. 0.58
        o[:20] = ALPHA_MIN * (1.0 + 1e-6)  # at the threshold: a radius of almost nothing
        scene["opacity_logits"] = torch.log(o / (1.0 - o))
    elif kind == "mixed":
        scene["log_scales"] = scene["log_scales"] + torch.randn(700, 1, generator=g) * 1.2
    return scene


def _projected(kind: str, seed: int, w: int, h: int):
    """(projection, opacities) of ``_scene(kind, seed)`` seen at w x h."""
    scene = _scene(kind, seed)
    viewmat, K = camera(w, h)
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, w, h)
    return proj, torch.sigmoid(scene["opacity_logits"])


def _tile_sets(bins, num: int) -> list[set[int]]:
    kept: list[set[int]] = [set() for _ in range(num)]
    for t in range(len(bins.offsets) - 1):
        for gid in bins.gaussian_ids[bins.offsets[t]:bins.offsets[t + 1]]:
            kept[int(gid)].add(t)
    return kept


def _box_tiles(box, tiles_x: int) -> set[int]:
    u0, v0, u1, v1 = (int(v) // TILE_SIZE for v in box)
    return {ty * tiles_x + tx for ty in range(v0, v1 + 1) for tx in range(u0, u1 + 1)}


CASES = [("needles", 1, 100, 70), ("faint", 2, 70, 45), ("mixed", 3, 100, 70), ("mixed", 4, 33, 17)]


@pytest.mark.parametrize("kind,seed,w,h", CASES)
def test_every_tile_a_gaussian_blends_in_is_kept(kind, seed, w, h):
    proj, opac = _projected(kind, seed, w, h)
    culled = bin_gaussians(proj, w, h, opac)
    whole = bin_gaussians(proj, w, h, opac, ellipse_cull=False)
    tiles_x = culled.tiles_x
    selected = _selected(proj, opac)
    reached = tiles_reached_reference(proj.means2d.numpy(), proj.conics.numpy(), opac.numpy(), proj.pixel_box.numpy(),
                                      tiles_x)
    kept = _tile_sets(culled, len(opac))
    for g in selected:
        assert reached[g] <= kept[g] <= _box_tiles(proj.pixel_box[g].numpy(), tiles_x), g
    n_reached = sum(len(reached[g]) for g in selected)
    assert 0 < n_reached <= culled.num_intersections < whole.num_intersections  # the cull drops pairs
    assert culled.num_intersections <= 1.6 * n_reached  # and stays near the tiles really reached
    # each tile's list is the whole box's list less the Gaussians culled from it, in the same (depth) order
    for t in range(len(culled.offsets) - 1):
        ours = culled.gaussian_ids[culled.offsets[t]:culled.offsets[t + 1]].tolist()
        theirs = whole.gaussian_ids[whole.offsets[t]:whole.offsets[t + 1]].tolist()
        assert [g for g in theirs if g in set(ours)] == ours


@pytest.mark.parametrize("kind,seed,w,h", CASES)
def test_culling_changes_no_image_weight_or_gradient(kind, seed, w, h):
    proj, opacities = _projected(kind, seed, w, h)
    colors = torch.rand(len(opacities), 4, generator=torch.Generator().manual_seed(seed))
    results = []
    for cull in (True, False):
        bins = bin_gaussians(proj, w, h, opacities, ellipse_cull=cull)
        leaves = [x.detach().clone().requires_grad_(True) for x in (proj.means2d, proj.conics, opacities, colors)]
        accum, alpha = blend_fast(*leaves, bins)
        (accum.square().sum() + alpha.sum()).backward()
        weights = blend_weights_fast(proj.means2d, proj.conics, opacities, bins, 8)
        results.append((accum.detach(), alpha.detach(), weights, [x.grad for x in leaves]))
    (acc_a, alpha_a, w_a, g_a), (acc_b, alpha_b, w_b, g_b) = results
    assert float(alpha_b.max()) > 0.5  # something is drawn
    assert torch.equal(acc_a, acc_b) and torch.equal(alpha_a, alpha_b)
    assert all(torch.equal(x, y) for x, y in zip(w_a, w_b))
    for x, y in zip(g_a, g_b):  # float32 per-tile partial sums in another grouping
        assert torch.allclose(x, y, rtol=1e-4, atol=1e-5 * float(y.abs().max()))


def _projection(means2d, conics, boxes) -> Projection:
    n = len(means2d)
    f64 = lambda a: torch.as_tensor(np.asarray(a, np.float64))  # noqa: E731
    return Projection(f64(means2d).reshape(n, 2), f64(conics).reshape(n, 3), f64(np.arange(1.0, n + 1)),
                      torch.ones(n, dtype=torch.bool), torch.as_tensor(np.asarray(boxes, np.int64).reshape(n, 4)),
                      torch.zeros(n, 3, dtype=torch.float64))


def test_degenerate_ellipses():
    """A faint Gaussian whose ellipse holds no pixel centre gets no tile; a degenerate conic keeps its whole box; an
    image-sized Gaussian keeps the rows beyond the trimmed ones whole; a needle along a diagonal loses its corners."""
    w, h = 96, 80  # 6 x 5 tiles
    means2d = [[-1.2, 30.0], [40.0, 40.0], [48.0, 40.0], [48.0, 40.0]]
    conics = [[100.0, 0.0, 100.0],  # tiny and (below) faint, centred left of the image
              [0.0, 0.0, 0.0],  # not positive definite
              [1e-4, 0.0, 1e-4],  # sigma 100 px: every tile
              [0.02, -0.0198, 0.02]]  # a needle along the diagonal x = y
    boxes = [[0, 28, 0, 31], [0, 0, 95, 79], [0, 0, 95, 79], [0, 0, 95, 79]]
    opac = torch.tensor([ALPHA_MIN * 1.01, 0.9, 0.9, 0.9])
    proj = _projection(means2d, conics, boxes)
    bins = bin_gaussians(proj, w, h, opac)
    kept = _tile_sets(bins, 4)
    assert kept[0] == set()
    assert kept[1] == kept[2] == set(range(30))
    assert kept[3] and len(kept[3]) < 30 and 0 in kept[3] and 29 in kept[3] and 5 not in kept[3]  # (5, 0) is a corner
    reached = tiles_reached_reference(proj.means2d.numpy(), proj.conics.numpy(), opac.numpy(), proj.pixel_box.numpy(),
                                      bins.tiles_x)
    assert all(r <= k for r, k in zip(reached, kept))
    colors = torch.rand(4, 3, generator=torch.Generator().manual_seed(0))
    a = blend_fast(proj.means2d, proj.conics, opac, colors, bins)
    b = blend_fast(proj.means2d, proj.conics, opac, colors, bin_gaussians(proj, w, h, opac, ellipse_cull=False))
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_bin_sorted_refuses_what_the_packed_box_cannot_hold():
    idx = np.array([0])
    box = np.array([[0, 0, 3, 3]])
    with pytest.raises(ValueError, match="tiles per side"):
        bin_sorted(idx, np.ones(1), box, TILE_SIZE, MAX_TILES_PER_SIDE + 1, 1)
    with pytest.raises(ValueError, match="means2d and conics together"):
        bin_sorted(idx, np.ones(1), box, TILE_SIZE, 4, 4, means2d=np.zeros((1, 2)))


def test_culling_changes_no_image_on_random_scenes():
    """Seeded fuzz: 40 scenes of random size, spread, scale, anisotropy (half with needles), opacity down to
    ALPHA_MIN and camera distance; the culled bins render every image bit for bit as whole boxes do."""
    pairs_culled = pairs_whole = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        n, w, h = int(rng.integers(50, 400)), int(rng.integers(8, 120)), int(rng.integers(8, 90))
        log_scales = rng.normal(-2.0, 0.5, (n, 3)) + rng.normal(0.0, float(rng.choice([0.2, 1.0, 2.0])), (n, 1))
        if seed % 2:
            log_scales[:, 0] += rng.uniform(0, 4, n)
            log_scales[:, 1] -= rng.uniform(0, 3, n)
        opacities = np.exp(rng.uniform(np.log(ALPHA_MIN), 0.0, n))
        opacities[: n // 10] = ALPHA_MIN * (1.0 + rng.uniform(0.0, 1e-3, n // 10))
        eye = rng.normal(size=3)
        viewmat, K = camera(w, h, eye=tuple(eye / np.linalg.norm(eye) * rng.uniform(1.5, 6.0)))
        f32 = lambda a: torch.from_numpy(np.asarray(a, np.float32))  # noqa: E731
        proj = project_gaussians_fast(f32(rng.normal(size=(n, 3)) * rng.choice([0.3, 1.0, 3.0])),
                                      f32(rng.normal(size=(n, 4))), f32(log_scales), viewmat, K, w, h)
        op, colors = f32(opacities), f32(rng.random((n, 3)))
        culled = bin_gaussians(proj, w, h, op)
        whole = bin_gaussians(proj, w, h, op, ellipse_cull=False)
        a = blend_fast(proj.means2d, proj.conics, op, colors, culled)
        b = blend_fast(proj.means2d, proj.conics, op, colors, whole)
        assert all(torch.equal(x, y) for x, y in zip(a, b)), seed
        pairs_culled, pairs_whole = pairs_culled + culled.num_intersections, pairs_whole + whole.num_intersections
    assert pairs_culled < 0.8 * pairs_whole
