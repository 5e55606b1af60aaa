"""Blend weights (fast vs reference), M = W S against the rasterizer, label maps on hand-made cases."""

from __future__ import annotations

import pytest
import torch

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render import BlendWeights, compute_blend_weights, rasterize, render_features, render_label_maps
from test_render_common import GEOMETRY, HEIGHT, WIDTH, camera, random_scene


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def weights_of(scene, top_k, backend="auto"):
    viewmat, K = camera()
    return compute_blend_weights(*(scene[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, top_k=top_k, backend=backend)


@pytest.mark.parametrize("top_k", [3, 64])
def test_fast_blend_weights_match_reference(top_k):
    scene = random_scene(60, 31)
    fast, ref = weights_of(scene, top_k, "fast"), weights_of(scene, top_k, "reference")
    assert fast.ids.dtype == torch.int64 and fast.weights.dtype == torch.float32
    assert torch.equal(fast.ids, ref.ids)
    assert float((fast.weights - ref.weights).abs().max()) <= 1e-5
    assert float((fast.residual_alpha - ref.residual_alpha).abs().max()) <= 1e-5
    assert bool(((fast.ids >= 0) == (fast.weights > 0)).all())


def test_render_features_reproduces_rasterizer_and_its_gradient():
    scene = random_scene(60, 32)
    viewmat, K = camera()
    bw = weights_of(scene, 64)
    assert float(bw.residual_alpha.max()) == 0.0, "K = 64 must cover every contributor"
    feats_a = scene["features"].clone().requires_grad_(True)
    feats_b = scene["features"].clone().requires_grad_(True)
    via_weights = render_features(bw, feats_a)
    direct = rasterize(*(scene[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, features=feats_b).image
    assert float((via_weights - direct).detach().abs().max()) <= 1e-5
    g = torch.randn(direct.shape, generator=torch.Generator().manual_seed(0))
    (via_weights * g).sum().backward()
    (direct * g).sum().backward()
    assert torch.allclose(feats_a.grad, feats_b.grad, atol=1e-4)


def test_truncated_weights_report_residual_alpha():
    scene = random_scene(60, 33)
    viewmat, K = camera()
    full = rasterize(*(scene[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT)
    bw = weights_of(scene, 2)
    assert float(bw.residual_alpha.max()) > 0.05, "two slots must leave contributors out"
    total = bw.weights.sum(-1) + bw.residual_alpha
    assert float((total - full.alpha).abs().max()) <= 1e-5
    # kept weights are the front-most ones: same as the first two of an untruncated list
    wide = weights_of(scene, 64)
    assert torch.equal(bw.ids, wide.ids[..., :2])


def hand_blend(ids, weights, residual=None) -> BlendWeights:
    ids = torch.tensor(ids, dtype=torch.int64)[None]
    weights = torch.tensor(weights, dtype=torch.float32)[None]
    residual = torch.zeros(ids.shape[:2]) if residual is None else torch.tensor(residual, dtype=torch.float32)[None]
    return BlendWeights(ids, weights, residual)


def test_label_maps_majority_threshold_and_ignore():
    # pixels: 0 majority of class 1 over a nearer class 0; 1 low alpha -> ignore;
    # 2 only an IGNORE-labelled Gaussian -> ignore; 3 an IGNORE Gaussian in front, class 1 behind -> ignore
    # (ignore is a label of its own in the vote: the unlabelled Gaussian occludes)
    blend = hand_blend(
        [[0, 1, 2], [0, -1, -1], [3, -1, -1], [3, 2, -1]],
        [[0.3, 0.25, 0.2], [0.2, 0.0, 0.0], [0.9, 0.0, 0.0], [0.7, 0.2, 0.0]],
    )
    semantic = torch.tensor([0, 1, 1, IGNORE_LABEL])
    instance = torch.tensor([10, 11, 12, 13])
    maps = render_label_maps(blend, semantic, instance, num_classes=3, min_alpha=0.5)
    assert maps.semantic[0].tolist() == [1, IGNORE_LABEL, IGNORE_LABEL, IGNORE_LABEL]
    assert maps.instance[0].tolist() == [10, IGNORE_LABEL, 13, 13]
    assert torch.allclose(maps.soft[0, 0], torch.tensor([0.3, 0.45, 0.0]))
    assert torch.allclose(maps.soft[0, 3], torch.tensor([0.0, 0.2, 0.0]))
    assert float(maps.soft[0, 2].sum()) == 0.0
    # residual alpha counts towards the threshold
    blend_r = hand_blend([[0, -1, -1]], [[0.3, 0.0, 0.0]], residual=[[0.3]])
    assert render_label_maps(blend_r, semantic, instance, 3, min_alpha=0.5).semantic.flatten().tolist() == [0]
    strict = render_label_maps(blend_r, semantic, instance, 3, min_alpha=0.7)
    assert strict.semantic.flatten().tolist() == [IGNORE_LABEL]


def test_label_maps_reject_bad_labels():
    blend = hand_blend([[0, 1]], [[0.5, 0.4]])
    with pytest.raises(ValueError, match="outside 0..2"):
        render_label_maps(blend, torch.tensor([0, 7]), torch.tensor([0, 1]), num_classes=3)
    with pytest.raises(ValueError, match="refer to Gaussian 1"):
        render_label_maps(blend, torch.tensor([0]), torch.tensor([0]), num_classes=3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_render_features_gradient_buffer_matches_autograd_gathers(dtype):
    """The one-buffer backward (index_add_ per slot) against autograd through each slot's gather: the same forward
    bits and the same gradient, with repeated Gaussians in a pixel, unused slots (-1) and Gaussians never drawn."""
    from seggaussian.render.blend import render_features_reference

    g = torch.Generator().manual_seed(3)
    ids = torch.randint(0, 40, (6, 7, 5), generator=g)
    ids[0, 0] = -1  # a pixel with no contributor
    ids[1, :, 3:] = -1  # unused trailing slots
    ids[2, 2] = 7  # one Gaussian in every slot of a pixel
    blend = BlendWeights(ids, torch.rand(6, 7, 5, generator=g), torch.zeros(6, 7))
    feats = torch.randn(50, 4, generator=g, dtype=dtype)  # rows 40..49 never drawn
    upstream = torch.randn(6, 7, 4, generator=g, dtype=dtype)
    results = []
    for fn in (render_features, render_features_reference):
        leaf = feats.clone().requires_grad_(True)
        out = fn(blend, leaf)
        (out * upstream).sum().backward()
        results.append((out.detach(), leaf.grad))
    (out_a, grad_a), (out_b, grad_b) = results
    assert torch.equal(out_a, out_b)
    assert torch.allclose(grad_a, grad_b, rtol=1e-6 if dtype == torch.float32 else 1e-12, atol=1e-6)
    assert not grad_a[40:].any() and grad_a[7].abs().sum() > 0
    # weights that need a gradient take the autograd path, and get one
    w = blend.weights.clone().requires_grad_(True)
    render_features(blend._replace(weights=w), feats).sum().backward()
    assert w.grad is not None and w.grad[0, 0].abs().sum() == 0 and w.grad.abs().sum() > 0
