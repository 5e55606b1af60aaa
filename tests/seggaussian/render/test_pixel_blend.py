"""Blend weights at sampled pixels (seggaussian.render.pixel_blend) against the whole view's cached-W definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.render import compute_blend_weights
from seggaussian.render.pixel_blend import (
    PixelBlendWeights, compute_pixel_blend_weights, pixel_blend_weights_reference,
)
from seggaussian.render.rasterize import camera_tensors


def make_scene(seed: int, n: int, width: int, height: int, scale=(0.01, 0.08)):
    rng = np.random.default_rng(seed)
    geometry = (torch.tensor(rng.uniform(-1, 1, (n, 3)) * [1.2, 1.0, 0.4], dtype=torch.float32),
                torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
                torch.tensor(np.log(rng.uniform(*scale, (n, 3))), dtype=torch.float32),
                torch.tensor(rng.normal(1.0, 2.0, n), dtype=torch.float32))
    focal = 0.8 * max(width, height)
    cam = Camera(intrinsics(focal, focal, width / 2, height / 2),
                 look_at([0.3, -0.2, 3.0], [0, 0, 0], up=(0, 1, 0)), width, height)
    return geometry, camera_tensors(cam)


def random_pixels(rng, count, width, height, duplicates=False):
    if duplicates:
        return torch.from_numpy(np.stack([rng.integers(0, width, count), rng.integers(0, height, count)], 1))
    flat = rng.choice(width * height, size=count, replace=False)
    return torch.from_numpy(np.stack([flat % width, flat // width], 1))


def assert_identical(a: PixelBlendWeights, b: PixelBlendWeights):
    assert a.ids.dtype == torch.int64 and a.weights.dtype == torch.float32
    assert torch.equal(a.ids, b.ids)
    assert torch.equal(a.weights, b.weights)
    assert torch.equal(a.residual_alpha, b.residual_alpha)


@pytest.mark.parametrize("seed,n,width,height,top_k", [
    (0, 3000, 64, 48, 16),  # whole tiles
    (1, 4000, 75, 37, 4),   # partial tiles at the right and bottom; small K: residual alpha > 0
    (2, 500, 17, 90, 16),   # one tile column and a bit
])
def test_pixel_weights_equal_the_full_view_bit_for_bit(seed, n, width, height, top_k):
    geometry, (viewmat, K) = make_scene(seed, n, width, height)
    rng = np.random.default_rng(seed)
    for pixels in (random_pixels(rng, width * height // 7, width, height),
                   random_pixels(rng, 300, width, height, duplicates=True),
                   torch.tensor([[0, 0], [width - 1, height - 1], [width - 1, 0], [0, height - 1]])):
        fast = compute_pixel_blend_weights(*geometry, viewmat, K, width, height, pixels, top_k)
        ref = pixel_blend_weights_reference(*geometry, viewmat, K, width, height, pixels, top_k)
        assert_identical(fast, ref)
    every = torch.stack(torch.meshgrid(torch.arange(width), torch.arange(height), indexing="xy"), -1).reshape(-1, 2)
    fast = compute_pixel_blend_weights(*geometry, viewmat, K, width, height, every, top_k)
    full = compute_blend_weights(*geometry, viewmat, K, width, height, top_k)
    assert torch.equal(fast.ids.reshape(height, width, top_k), full.ids)
    assert torch.equal(fast.weights.reshape(height, width, top_k), full.weights)
    assert (fast.ids[:, 0] >= 0).float().mean() > 0.3  # the scene covers the view: the comparison has content
    if top_k == 4:
        assert (fast.residual_alpha > 0).sum() > 10


def test_degenerate_scenes_and_pixel_sets():
    geometry, (viewmat, K) = make_scene(3, 400, 40, 30)
    pixels = random_pixels(np.random.default_rng(0), 100, 40, 30)
    empty = compute_pixel_blend_weights(*geometry, viewmat, K, 40, 30, torch.zeros(0, 2, dtype=torch.int64), 8)
    assert empty.ids.shape == (0, 8) and empty.weights.shape == (0, 8) and empty.residual_alpha.shape == (0,)
    # no Gaussian in front of the camera
    behind = (geometry[0] + torch.tensor([0.0, 0.0, 10.0]),) + geometry[1:]
    none = compute_pixel_blend_weights(*behind, viewmat, K, 40, 30, pixels, 8)
    assert bool((none.ids == -1).all()) and bool((none.weights == 0).all())
    # no Gaussians at all
    zero = tuple(t[:0] for t in geometry)
    assert bool((compute_pixel_blend_weights(*zero, viewmat, K, 40, 30, pixels, 8).ids == -1).all())
    # tiny scales (sub-pixel footprints, the 0.3 px dilation dominates) and opaque Gaussians
    tiny = (geometry[0], geometry[1], torch.full_like(geometry[2], -20.0), torch.full_like(geometry[3], 8.0))
    assert_identical(compute_pixel_blend_weights(*tiny, viewmat, K, 40, 30, pixels, 8),
                     pixel_blend_weights_reference(*tiny, viewmat, K, 40, 30, pixels, 8))


@pytest.mark.parametrize("pixels,message", [
    (torch.tensor([[40, 0]]), "outside the 40x30 image"),
    (torch.tensor([[0, -1]]), "outside the 40x30 image"),
    (torch.tensor([[0.5, 1.0]]), "must be integers"),
    (torch.tensor([0, 1]), "must be [P, 2]"),
])
def test_bad_pixels_are_rejected_with_a_clear_error(pixels, message):
    geometry, (viewmat, K) = make_scene(4, 50, 40, 30)
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        compute_pixel_blend_weights(*geometry, viewmat, K, 40, 30, pixels, 8)


def test_semantic_map_forward_and_backward_equal_the_cached_w_definition(tmp_path):
    """M = W S at the sampled pixels: on the fly vs. the whole view's W written to disk and read back as the
    trainer used to (int32 ids, float32 weights in safetensors), forward and gradient bit for bit."""
    from safetensors.torch import load_file, save_file

    from ovgaussian.train.step_losses import render_pixels

    width, height, top_k = 70, 52, 16
    geometry, (viewmat, K) = make_scene(5, 2500, width, height)
    full = compute_blend_weights(*geometry, viewmat, K, width, height, top_k)
    path = tmp_path / "view.safetensors"
    save_file({"ids": full.ids.to(torch.int32), "weights": full.weights}, str(path))
    cached = load_file(str(path))
    rng = np.random.default_rng(6)
    pixels = random_pixels(rng, 900, width, height)
    flat = pixels[:, 1] * width + pixels[:, 0]
    cached_ids = cached["ids"].long().reshape(-1, top_k)[flat]
    cached_weights = cached["weights"].reshape(-1, top_k)[flat]
    on_the_fly = compute_pixel_blend_weights(*geometry, viewmat, K, width, height, pixels, top_k)

    semantic = torch.randn(geometry[0].shape[0], 16, requires_grad=True)
    upstream = torch.randn(pixels.shape[0], 16)
    m_cached = render_pixels(cached_ids, cached_weights, semantic)
    (g_cached,) = torch.autograd.grad((m_cached * upstream).sum(), semantic)
    m_fly = render_pixels(on_the_fly.ids, on_the_fly.weights, semantic)
    (g_fly,) = torch.autograd.grad((m_fly * upstream).sum(), semantic)
    assert torch.equal(m_fly, m_cached) and torch.equal(g_fly, g_cached)
    assert m_fly.abs().sum() > 0 and (g_fly != 0).any(dim=1).sum() > 100


def test_compiled_evaluation_render_equals_render_features():
    from seggaussian.render import render_features
    from seggaussian.render.pixel_blend import ViewBlender, render_features_no_grad

    geometry, (viewmat, K) = make_scene(7, 1500, 50, 40)
    band = ViewBlender(*geometry, viewmat, K, 50, 40, 16).rows(3, 29)
    features = torch.randn(1500, 16)
    expected = render_features(band, features).numpy()
    got = render_features_no_grad(band.ids.numpy(), band.weights.numpy(), features.numpy())
    assert got.shape == (26, 50, 16) and np.abs(expected).sum() > 0
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="refer to Gaussian"):
        render_features_no_grad(band.ids.numpy(), band.weights.numpy(), features[:10].numpy())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (no GPU on this machine)")
def test_cuda_inputs_give_the_cpu_weights_and_the_same_semantic_map():
    """Geometry and semantic vectors on the GPU: W (computed on the CPU) is identical, and M = W S on the
    GPU matches the CPU within float tolerance, forward and backward."""
    from ovgaussian.train.step_losses import render_pixels

    width, height = 60, 44
    geometry, (viewmat, K) = make_scene(8, 1500, width, height)
    pixels = random_pixels(np.random.default_rng(8), 500, width, height)
    cpu = compute_pixel_blend_weights(*geometry, viewmat, K, width, height, pixels, 16)
    gpu = compute_pixel_blend_weights(*(t.cuda() for t in geometry), viewmat.cuda(), K.cuda(), width, height,
                                      pixels.cuda(), 16)
    assert_identical(gpu, cpu)
    semantic = torch.randn(1500, 16, requires_grad=True)
    semantic_gpu = semantic.detach().cuda().requires_grad_(True)
    m_cpu = render_pixels(cpu.ids, cpu.weights, semantic)
    m_gpu = render_pixels(gpu.ids.cuda(), gpu.weights.cuda(), semantic_gpu)
    torch.testing.assert_close(m_gpu.cpu(), m_cpu, rtol=1e-5, atol=1e-6)
    upstream = torch.randn_like(m_cpu)
    (g_cpu,) = torch.autograd.grad((m_cpu * upstream).sum(), semantic)
    (g_gpu,) = torch.autograd.grad((m_gpu * upstream.cuda()).sum(), semantic_gpu)
    torch.testing.assert_close(g_gpu.cpu(), g_cpu, rtol=1e-5, atol=1e-6)
