"""Projection: numba kernels against the torch version (values, culling, gradients), SH evaluation."""

from __future__ import annotations

import math

import pytest
import torch

from seggaussian.core.constants import SH_C0
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.projection import project_gaussians
from seggaussian.render.sh import sh_to_colors
from test_render_common import HEIGHT, WIDTH, camera, random_scene


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def degenerate_scene():
    scene = random_scene(300, 3, dtype=torch.float64, spread=1.5)
    scene["log_scales"][:5] = -math.inf
    scene["log_scales"][5:10] = 88.0
    scene["log_scales"][10:12] = 200.0
    scene["quats"][12:15] = 0.0
    scene["log_scales"][16:19, 1] = math.inf  # needles: a*c - b^2 would cancel catastrophically
    scene["means"][15] = torch.tensor([0.3, -3.0, 0.6], dtype=torch.float64)  # the camera centre
    return scene


def project_with_grads(fn, scene):
    viewmat, K = camera()
    leaves = [scene[k].clone().requires_grad_(True) for k in ("means", "quats", "log_scales")]
    proj = fn(*leaves, viewmat, K, WIDTH, HEIGHT)
    g = torch.Generator().manual_seed(0)
    loss = sum((x * torch.randn(x.shape, generator=g, dtype=x.dtype)).sum()
               for x in (proj.means2d, proj.conics, proj.depths, proj.view_dirs))
    loss.backward()
    return proj, [x.grad for x in leaves]


def test_fast_projection_matches_torch():
    scene = degenerate_scene()
    ref, ref_grads = project_with_grads(project_gaussians, scene)
    fast, fast_grads = project_with_grads(project_gaussians_fast, scene)
    assert 50 < int(ref.valid.sum()) < 300, "both culled and kept Gaussians"
    assert torch.equal(ref.valid, fast.valid)
    assert torch.equal(ref.pixel_box[ref.valid], fast.pixel_box[fast.valid])  # meaningless where culled
    for name in ("means2d", "conics", "depths", "view_dirs"):
        a, b = getattr(ref, name).detach(), getattr(fast, name).detach()
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12), name
    for a, b in zip(ref_grads, fast_grads):
        assert torch.isfinite(b).all()
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-10 * float(a.abs().max()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fast_projection_matches_torch_across_blocks(dtype):
    """The kernels work in blocks of _LANE_BLOCK Gaussians staged as columns: several blocks and a partial last
    one, with degenerate rows at block edges, give the reference's outputs and gradients row for row."""
    from seggaussian.render.projection_lanes import LANE_BLOCK as _LANE_BLOCK

    n = 2 * _LANE_BLOCK + 217
    scene = random_scene(n, 11, dtype=dtype, spread=1.5)
    for start in (0, _LANE_BLOCK - 3, 2 * _LANE_BLOCK + 200):  # degenerate rows at block edges
        scene["log_scales"][start] = -math.inf
        scene["log_scales"][start + 1, 2] = 200.0
        scene["quats"][start + 2] = 0.0
    ref, ref_grads = project_with_grads(project_gaussians, scene)
    fast, fast_grads = project_with_grads(project_gaussians_fast, scene)
    ref, fast = ref._replace(**{k: getattr(ref, k).detach() for k in ("means2d", "conics", "depths", "view_dirs")}), \
        fast._replace(**{k: getattr(fast, k).detach() for k in ("means2d", "conics", "depths", "view_dirs")})
    assert 0 < int(ref.valid.sum()) < n
    assert torch.equal(ref.valid, fast.valid)
    assert torch.equal(ref.pixel_box[ref.valid], fast.pixel_box[fast.valid])
    assert bool((fast.pixel_box[~fast.valid] == torch.tensor([0, 0, -1, -1])).all())
    tolerance = 1e-12 if dtype == torch.float64 else 1e-6  # float32 gradients are rounded to float32
    for name in ("means2d", "conics", "depths", "view_dirs"):
        assert torch.allclose(getattr(ref, name), getattr(fast, name), rtol=1e-12, atol=1e-12), name
    for a, b in zip(ref_grads, fast_grads):
        assert torch.isfinite(b).all()
        assert torch.allclose(a, b, rtol=tolerance, atol=tolerance * float(a.abs().max()))


def test_polynomial_exp_matches_math_exp_over_the_clamped_range():
    from seggaussian.core.constants import LOG_SCALE_FLOAT32_MAX
    from seggaussian.render.projection import LOG_SCALE_MIN
    from seggaussian.render.projection_lanes import _exp_scale

    xs = [LOG_SCALE_MIN, LOG_SCALE_FLOAT32_MAX, 0.0, -1e-300, 1e-300]
    xs += [LOG_SCALE_MIN + (LOG_SCALE_FLOAT32_MAX - LOG_SCALE_MIN) * k / 9973 for k in range(9974)]
    worst = max(abs(_exp_scale(x) / math.exp(x) - 1.0) for x in xs)
    assert worst < 1e-13, worst
    assert _exp_scale(0.0) == 1.0


def test_fast_projection_gradcheck():
    scene = random_scene(6, 5, dtype=torch.float64, spread=0.4)
    scene["means"][0] = torch.tensor([2.4, 0.0, 0.0], dtype=torch.float64)  # beyond the Jacobian clamp
    scene["log_scales"][0] = math.log(0.6)  # ... but wide enough to reach the image
    viewmat, K = camera()

    def fn(means, quats, log_scales):
        p = project_gaussians_fast(means, quats, log_scales, viewmat, K, WIDTH, HEIGHT)
        return p.means2d, p.conics, p.depths, p.view_dirs

    inputs = tuple(scene[k].clone().requires_grad_(True) for k in ("means", "quats", "log_scales"))
    assert bool(project_gaussians_fast(*(x.detach() for x in inputs), viewmat, K, WIDTH, HEIGHT).valid.all())
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_sh_degree_zero_is_the_dc_colour_and_clamped():
    sh = torch.tensor([[[1.0, -3.0, 0.0]]])
    colors = sh_to_colors(sh, torch.tensor([[0.0, 0.0, 1.0]]))
    assert torch.allclose(colors, torch.tensor([[0.5 + SH_C0, 0.0, 0.5]]))


def test_sh_matches_direct_basis_formula():
    """Degree-1 band: -C1 y, C1 z, -C1 x (3DGS sign convention), evaluated on unit directions."""
    dirs = torch.nn.functional.normalize(torch.randn(5, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    sh = torch.zeros(5, 4, 3)
    sh[:, 1, 0], sh[:, 2, 1], sh[:, 3, 2] = 1.0, 1.0, 1.0
    c1 = 0.4886025119029199
    expected = torch.stack([-c1 * dirs[:, 1], c1 * dirs[:, 2], -c1 * dirs[:, 0]], 1) + 0.5
    assert torch.allclose(sh_to_colors(sh, dirs), expected.clamp_min(0), atol=1e-6)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_evaluate_sh_matches_the_numpy_basis_and_gradcheck(degree):
    """The compiled contraction (float64) against the per-coefficient sum over the numpy evaluation of the same
    polynomials (``frames.sh_rotation.sh_basis``), with bands above ``degree`` ignored; gradients (coefficients and
    directions) by finite differences. The polynomials themselves are checked by the rotation tests of
    tests/seggaussian/frames (each band maps onto itself under any rotation) and the explicit band-1 test above."""
    import numpy as np

    from seggaussian.frames.sh_rotation import sh_basis as numpy_basis
    from seggaussian.render.sh import evaluate_sh

    gen = torch.Generator().manual_seed(degree)
    dirs = torch.nn.functional.normalize(torch.randn(7, 3, generator=gen, dtype=torch.float64), dim=1)
    sh = torch.randn(7, 16, 3, generator=gen, dtype=torch.float64)
    basis = numpy_basis(dirs.numpy(), degree)  # [7, (degree + 1)^2]
    expected = sum(basis[:, k : k + 1] * sh[:, k].numpy() for k in range(basis.shape[1]))
    assert np.allclose(evaluate_sh(sh, dirs, degree).numpy(), expected, atol=1e-12)
    sh.requires_grad_(True)
    dirs.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s, d: evaluate_sh(s, d, degree), (sh, dirs), eps=1e-6, atol=1e-8)


@pytest.mark.parametrize("n", [0, 1, 300])
@pytest.mark.parametrize("degree", [0, 2, 3])
def test_evaluate_sh_kernels_match_the_torch_reference(n, degree):
    """The compiled contraction against the per-coefficient torch sum, forward and backward, in float32, with
    degree-3 coefficients evaluated at a lower degree (the unused bands get zero gradient), on empty and one-row input."""
    from seggaussian.render.sh import evaluate_sh, evaluate_sh_reference

    gen = torch.Generator().manual_seed(n + degree)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=1)
    sh = torch.randn(n, 16, 3, generator=gen)
    weight = torch.randn(n, 3, generator=gen)
    results = []
    for fn in (evaluate_sh, evaluate_sh_reference):
        s, d = sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)
        out = fn(s, d, degree)
        (out * weight).sum().backward()
        results.append((out.detach(), s.grad, d.grad))
    for fast, ref in zip(*results):
        if ref is None:  # degree 0: the colour does not depend on the direction
            assert degree == 0 and (fast is None or not fast.any())
            continue
        assert fast.shape == ref.shape and fast.dtype == ref.dtype
        assert torch.allclose(fast, ref, atol=1e-5, rtol=1e-5)
    assert not results[0][1][:, (degree + 1) ** 2 :].any()


def test_tile_lists_match_a_naive_binning():
    import numpy as np

    from seggaussian.core.constants import TILE_SIZE
    from seggaussian.render.tiles import bin_gaussians

    scene = random_scene(400, 13, dtype=torch.float64, spread=1.0)
    viewmat, K = camera(100, 70)
    proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, 100, 70)
    bins = bin_gaussians(proj, 100, 70, ellipse_cull=False)  # whole boxes (the cull: test_ellipse_cull.py)
    assert (bins.tiles_x, bins.tiles_y) == (7, 5)
    valid = proj.valid.numpy()
    order = [g for g in np.argsort(proj.depths.numpy(), kind="stable") if valid[g]]
    box = proj.pixel_box.numpy() // TILE_SIZE
    for ty in range(bins.tiles_y):
        for tx in range(bins.tiles_x):
            t = ty * bins.tiles_x + tx
            expected = [g for g in order if box[g, 0] <= tx <= box[g, 2] and box[g, 1] <= ty <= box[g, 3]]
            assert bins.gaussian_ids[bins.offsets[t]:bins.offsets[t + 1]].tolist() == expected, (tx, ty)
    assert bins.num_intersections > 400
