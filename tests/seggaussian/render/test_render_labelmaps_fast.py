"""The numba label-map vote against the vectorized torch reference."""

import numpy as np
import pytest
import torch

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render import render_label_maps
from seggaussian.render.results import BlendWeights
from seggaussian.render.labelmaps import render_label_maps_reference


def random_blend(seed, h=13, w=17, k=8, n=30, quantized=False):
    rng = np.random.default_rng(seed)
    ids = rng.integers(-1, n, size=(h, w, k))
    weights = rng.random((h, w, k)).astype(np.float32) * 0.2
    if quantized:  # many exact ties between labels
        weights = np.round(weights * 8) / 8
    weights[ids < 0] = 0
    residual = (rng.random((h, w)) * 0.3).astype(np.float32)
    return BlendWeights(torch.as_tensor(ids), torch.as_tensor(weights), torch.as_tensor(residual)), rng


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("quantized", [False, True])
def test_fast_label_maps_match_reference(seed, quantized):
    blend, rng = random_blend(seed, quantized=quantized)
    semantic = rng.integers(0, 5, size=30)
    semantic[rng.random(30) < 0.2] = IGNORE_LABEL
    instance = rng.integers(0, 9, size=30)
    instance[rng.random(30) < 0.2] = IGNORE_LABEL
    fast = render_label_maps(blend, torch.as_tensor(semantic), torch.as_tensor(instance), 5, min_alpha=0.4)
    ref = render_label_maps_reference(blend, torch.as_tensor(semantic), torch.as_tensor(instance), 5, min_alpha=0.4)
    assert torch.equal(fast.semantic, ref.semantic)
    assert torch.equal(fast.instance, ref.instance)
    torch.testing.assert_close(fast.soft, ref.soft, rtol=1e-6, atol=1e-7)
    assert (fast.semantic == IGNORE_LABEL).any() and (fast.semantic != IGNORE_LABEL).any()


def test_empty_view_and_bad_labels():
    blend = BlendWeights(torch.full((4, 5, 3), -1), torch.zeros(4, 5, 3), torch.zeros(4, 5))
    maps = render_label_maps(blend, torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), 3)
    assert (maps.semantic == IGNORE_LABEL).all() and (maps.instance == IGNORE_LABEL).all()
    assert maps.soft.shape == (4, 5, 3) and float(maps.soft.sum()) == 0.0
    blend, _ = random_blend(0, n=30)
    with pytest.raises(ValueError, match="outside"):
        render_label_maps(blend, torch.full((30,), 7), torch.zeros(30, dtype=torch.int64), 5)


@pytest.mark.parametrize("backend", ["fast", "reference"])
def test_opaque_unlabelled_gaussian_in_front_occludes(backend):
    # pixel 0: an opaque unlabelled Gaussian (weight 0.99) in front of a labelled one (0.0099) -> ignore,
    # semantic and instance; pixel 1: the same two in the other depth order -> the labelled one wins;
    # pixel 2: two labelled Gaussians of class 1 behind an unlabelled one outweigh it -> class 1
    ids = torch.tensor([[[0, 1, 2], [1, 0, -1], [0, 1, 2]]])
    weights = torch.tensor([[[0.99, 0.0099, 0.0], [0.99, 0.0099, 0.0], [0.4, 0.3, 0.29]]])
    blend = BlendWeights(ids, weights, torch.zeros(1, 3))
    semantic = torch.tensor([IGNORE_LABEL, 1, 1])
    instance = torch.tensor([IGNORE_LABEL, 7, 8])
    maps = render_label_maps(blend, semantic, instance, 3, min_alpha=0.5, backend=backend)
    assert maps.semantic[0].tolist() == [IGNORE_LABEL, 1, 1]
    # instance 7 (0.3) and 8 (0.29) each lose to ignore (0.4) on pixel 2
    assert maps.instance[0].tolist() == [IGNORE_LABEL, 7, IGNORE_LABEL]
    torch.testing.assert_close(maps.soft[0, 0], torch.tensor([0.0, 0.0099, 0.0]))


@pytest.mark.parametrize("seed", range(3))
def test_fast_matches_reference_when_ignore_dominates(seed):
    # half the Gaussians unlabelled: many pixels where ignore wins, ties between ignore and a class
    blend, rng = random_blend(seed + 10, quantized=True)
    semantic = rng.integers(0, 3, size=30)
    semantic[rng.random(30) < 0.5] = IGNORE_LABEL
    instance = np.where(semantic == IGNORE_LABEL, IGNORE_LABEL, rng.integers(0, 4, size=30))
    fast = render_label_maps(blend, torch.as_tensor(semantic), torch.as_tensor(instance), 3, min_alpha=0.1)
    ref = render_label_maps_reference(blend, torch.as_tensor(semantic), torch.as_tensor(instance), 3, min_alpha=0.1)
    assert torch.equal(fast.semantic, ref.semantic) and torch.equal(fast.instance, ref.instance)
    torch.testing.assert_close(fast.soft, ref.soft, rtol=1e-6, atol=1e-7)
    # where an ignore-labelled slot carries strictly more weight than every class, the pixel is ignore
    ids, w = blend.ids.numpy(), blend.weights.numpy()
    lab = np.where(ids >= 0, semantic[np.clip(ids, 0, None)], -1)
    ignore_w = np.where(lab == IGNORE_LABEL, w, 0).sum(-1)
    class_w = np.stack([np.where(lab == c, w, 0).sum(-1) for c in range(3)], -1).max(-1)
    won = ignore_w > class_w
    assert won.any() and (fast.semantic.numpy()[won] == IGNORE_LABEL).all()
