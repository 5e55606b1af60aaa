"""seggaussian.render.rasterize: fast (numba) path against the per-pixel torch reference, invariances."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seggaussian.core.constants import ALPHA_MIN
from seggaussian.render import rasterize, render_gaussians
from seggaussian.render.projection import project_gaussians
from seggaussian.render.reference import blend_reference
from test_render_common import GEOMETRY, HEIGHT, WIDTH, camera, random_scene


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def render_with_grads(scene, backend, *, use_sh=True, sh_degree=None, background=None, seed=7, **cam):
    viewmat, K = camera(**cam)
    leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
    color_kw = {"sh": leaves["sh"], "sh_degree": sh_degree} if use_sh else {"features": leaves["features"]}
    out = rasterize(*(leaves[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, background=background,
                    backend=backend, **color_kw)
    g = torch.Generator().manual_seed(seed)
    loss = (out.image * torch.randn(out.image.shape, generator=g, dtype=out.image.dtype)).sum()
    loss = loss + 0.7 * (out.alpha * torch.randn(out.alpha.shape, generator=g, dtype=out.alpha.dtype)).sum()
    loss = loss + 0.2 * (out.depth * torch.randn(out.depth.shape, generator=g, dtype=out.depth.dtype)).sum()
    loss.backward()
    grads = {k: (v.grad if v.grad is not None else torch.zeros_like(v)) for k, v in leaves.items()}
    return out, grads


def assert_grads_close(fast: torch.Tensor, ref: torch.Tensor, name: str, rtol: float = 1e-3) -> None:
    scale = float(ref.abs().max()) or 1.0
    err = float((fast.double() - ref.double()).abs().max())
    assert err <= rtol * scale, f"{name}: max |fast - ref| = {err:.3g}, max |ref| = {scale:.3g}"


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("use_sh", [True, False])
def test_fast_matches_reference(seed, use_sh):
    scene = random_scene(60, seed, sh_degree=2)
    background = torch.tensor([0.1, 0.5, 0.9] if use_sh else [0.2] * 5)
    ref, ref_grads = render_with_grads(scene, "reference", use_sh=use_sh, background=background)
    fast, fast_grads = render_with_grads(scene, "fast", use_sh=use_sh, background=background)
    assert ref.alpha.max() > 0.5, "scene must actually cover pixels"
    for name in ("image", "alpha", "depth"):
        diff = float((getattr(fast, name) - getattr(ref, name)).detach().abs().max())
        assert diff <= 1e-4, f"{name}: max diff {diff}"
    for name in (*GEOMETRY, "sh" if use_sh else "features"):
        assert float(ref_grads[name].abs().max()) > 0
        assert_grads_close(fast_grads[name], ref_grads[name], name)


def test_torch_tile_backend_matches_reference():
    scene = random_scene(40, 3)
    ref, ref_grads = render_with_grads(scene, "reference")
    tiles, tile_grads = render_with_grads(scene, "torch")
    assert float((tiles.image - ref.image).abs().max()) <= 1e-4
    for name in (*GEOMETRY, "sh"):
        assert_grads_close(tile_grads[name], ref_grads[name], name)


def test_reference_gradcheck_float64():
    scene = random_scene(4, 11, dtype=torch.float64, sh_degree=1, spread=0.3)
    scene["log_scales"] = scene["log_scales"] + 0.8  # few large Gaussians: every one covers pixels
    viewmat, K = camera(8, 6)
    names = (*GEOMETRY, "sh")

    def fn(*xs):
        d = dict(zip(names, xs))
        out = rasterize(*(d[k] for k in GEOMETRY), viewmat, K, 8, 6, sh=d["sh"], backend="reference")
        return out.image, out.alpha, out.depth

    inputs = tuple(scene[k].clone().requires_grad_(True) for k in names)
    covered = fn(*(x.detach() for x in inputs))[1]
    assert float(covered.min()) < 0.5 < float(covered.max()), "every kind of pixel must be exercised"
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)

    def fn_features(feats, opacity_logits):
        out = rasterize(scene["means"], scene["quats"], scene["log_scales"], opacity_logits, viewmat, K, 8, 6,
                        features=feats, backend="reference")
        return out.image

    assert torch.autograd.gradcheck(
        fn_features,
        (scene["features"].clone().requires_grad_(True), scene["opacity_logits"].clone().requires_grad_(True)),
        eps=1e-6, atol=1e-5, rtol=1e-4,
    )


def test_reference_blend_matches_hand_computation():
    """Two Gaussians on one pixel: out = c1 a1 + c2 a2 (1 - a1), alpha = 1 - (1 - a1)(1 - a2)."""
    means2d = torch.tensor([[0.5, 0.5], [0.5, 0.5]], dtype=torch.float64)
    conics = torch.tensor([[1.0, 0.0, 1.0], [1.0, 0.0, 1.0]], dtype=torch.float64)
    opac = torch.tensor([0.5, 0.8], dtype=torch.float64)
    colors = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    depths = torch.tensor([2.0, 1.0], dtype=torch.float64)  # second Gaussian is in front
    accum, alpha = blend_reference(means2d, conics, opac, colors, depths, torch.tensor([True, True]), 1, 1)
    assert torch.allclose(accum[0, 0], torch.tensor([0.5 * 0.2, 0.8], dtype=torch.float64))
    assert torch.allclose(alpha[0, 0], torch.tensor(1 - 0.2 * 0.5, dtype=torch.float64))


def test_transmittance_stop_and_alpha_floor():
    """An opaque stack stops once T would fall below 1e-4; sub-ALPHA_MIN Gaussians are skipped."""
    n = 6
    means2d = torch.full((n, 2), 0.5, dtype=torch.float64)
    conics = torch.tensor([[1.0, 0.0, 1.0]] * n, dtype=torch.float64)
    opac = torch.tensor([0.99, 0.99, 0.5 * ALPHA_MIN, 0.99, 0.99, 0.99], dtype=torch.float64)
    colors = torch.eye(n, dtype=torch.float64)
    depths = torch.arange(n, dtype=torch.float64)
    accum, alpha = blend_reference(means2d, conics, opac, colors, depths, torch.ones(n, dtype=torch.bool), 1, 1)
    c = accum[0, 0]
    assert c[2] == 0  # below ALPHA_MIN
    assert torch.allclose(c[:2], torch.tensor([0.99, 0.99 * 0.01], dtype=torch.float64))
    assert c[3] == 0 and c[4] == 0  # T = 1e-4 before the 4th: 1e-4 * 0.01 < 1e-4 -> stop
    assert torch.allclose(alpha[0, 0], torch.tensor(1 - 1e-4, dtype=torch.float64))


def test_sh_degree_step_up():
    scene = random_scene(30, 4, sh_degree=3)
    viewmat, K = camera()
    geo = [scene[k] for k in GEOMETRY]
    low = rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"], sh_degree=1)
    cut = rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"][:, :4])
    full = rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"])
    assert torch.equal(low.image, cut.image)
    assert float((full.image - low.image).abs().max()) > 1e-3
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"][:, :4], sh_degree=2)


def test_permutation_invariance():
    scene = random_scene(80, 5)
    viewmat, K = camera()
    perm = torch.randperm(80, generator=torch.Generator().manual_seed(0))
    a = rasterize(*(scene[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, sh=scene["sh"])
    b = rasterize(*(scene[k][perm] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, sh=scene["sh"][perm])
    assert torch.allclose(a.image, b.image, atol=1e-6)
    assert torch.allclose(a.depth, b.depth, atol=1e-5)


def test_moving_scene_and_camera_together():
    """Far from the origin (float64 inputs): same image, same binning as next to the origin."""
    scene = random_scene(80, 6, dtype=torch.float64)
    viewmat, K = camera()
    offset = torch.tensor([12345.25, -23456.5, 3456.75], dtype=torch.float64)
    shift = torch.eye(4, dtype=torch.float64)
    shift[:3, 3] = -offset
    far_viewmat = viewmat @ shift
    geo = [scene[k] for k in GEOMETRY]
    near = rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"])
    far = rasterize(geo[0] + offset, *geo[1:], far_viewmat, K, WIDTH, HEIGHT, sh=scene["sh"])
    assert float((near.image - far.image).abs().max()) <= 1e-5
    p_near = project_gaussians(*geo[:3], viewmat, K, WIDTH, HEIGHT)
    p_far = project_gaussians(geo[0] + offset, *geo[1:3], far_viewmat, K, WIDTH, HEIGHT)
    assert torch.equal(p_near.pixel_box, p_far.pixel_box) and torch.equal(p_near.valid, p_far.valid)


def test_fast_backward_is_deterministic_across_thread_counts():
    import numba

    scene = random_scene(120, 8)
    out1, g1 = render_with_grads(scene, "fast")
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        out2, g2 = render_with_grads(scene, "fast")
    finally:
        numba.set_num_threads(threads)
    assert torch.equal(out1.image, out2.image)
    for name in g1:
        assert torch.equal(g1[name], g2[name]), name


def test_bad_inputs_raise_clear_errors():
    scene = random_scene(5, 0)
    viewmat, K = camera()
    geo = [scene[k] for k in GEOMETRY]
    bad = geo[0].clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="means holds NaN"):
        rasterize(bad, *geo[1:], viewmat, K, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="quats has shape"):
        rasterize(geo[0], geo[1][:, :3], *geo[2:], viewmat, K, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="either features or sh"):
        rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"], features=scene["features"])
    with pytest.raises(ValueError, match="background"):
        rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"], background=torch.zeros(5))


def test_render_gaussians_numpy_types():
    from seggaussian.core.cameras import Camera
    from seggaussian.core.gaussians import Gaussians

    scene = random_scene(30, 9)
    gaussians = Gaussians.from_arrays(*(scene[k] for k in (*GEOMETRY, "sh")))
    viewmat, K = camera()
    cam = Camera(K.numpy(), viewmat.numpy(), WIDTH, HEIGHT)
    out = render_gaussians(gaussians, cam)
    direct = rasterize(*(scene[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, sh=scene["sh"])
    assert out.image.shape == (HEIGHT, WIDTH, 3)
    assert np.allclose(out.image.numpy(), direct.image.numpy(), atol=1e-6)


def test_gsplat_backend_when_available():
    from seggaussian.render.gsplat_backend import GsplatUnavailable, gsplat_available

    scene = random_scene(50, 12)
    viewmat, K = camera()
    geo = [scene[k] for k in GEOMETRY]
    ok, reason = gsplat_available()
    if not ok:
        with pytest.raises(GsplatUnavailable, match="gsplat"):
            rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"], backend="gsplat")
        pytest.skip(reason)
    ours = rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"])
    theirs = rasterize(*geo, viewmat, K, WIDTH, HEIGHT, sh=scene["sh"], backend="gsplat")
    # gsplat has no per-pixel 3-sigma cutoff: faint tails differ
    assert float((ours.image - theirs.image).abs().mean()) < 1e-2
