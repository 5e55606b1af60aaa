"""Label images voted inside the walk (``render_label_images``) against the two steps: blend weights, then the vote."""

from __future__ import annotations

import pytest
import torch

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render.label_images import render_label_images
from test_render_common import GEOMETRY, HEIGHT, WIDTH, camera, random_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def labels_of(num, seed, classes=4, ignore_share=0.25):
    g = torch.Generator().manual_seed(seed)
    semantic = torch.randint(0, classes, (num,), generator=g)
    semantic[torch.rand(num, generator=g) < ignore_share] = IGNORE_LABEL
    instance = torch.randint(0, 3 * classes, (num,), generator=g)
    instance[torch.rand(num, generator=g) < ignore_share] = IGNORE_LABEL
    return semantic, instance


def both(scene, semantic, instance, classes, top_k, min_alpha, width=WIDTH, height=HEIGHT):
    viewmat, K = camera(width, height)
    args = (*(scene[k] for k in GEOMETRY), viewmat, K, width, height, semantic, instance, classes, top_k, min_alpha)
    return render_label_images(*args, backend="fast"), render_label_images(*args, backend="reference")


@pytest.mark.parametrize("top_k", [1, 2, 4, 16])
@pytest.mark.parametrize("min_alpha", [0.0, 0.3, 0.5, 1.0])
def test_walk_vote_equals_blend_weights_then_vote(top_k, min_alpha):
    # a dense cluster: most pixels have more contributors than top_k, so the early stop is taken where the slots sum
    # to min_alpha (never at min_alpha 1.0, always once the slots fill at 0.0)
    scene = random_scene(400, 7 + top_k, spread=0.35)
    semantic, instance = labels_of(400, top_k)
    fast, ref = both(scene, semantic, instance, 4, top_k, min_alpha, 48, 40)
    assert torch.equal(fast.semantic, ref.semantic)
    assert torch.equal(fast.instance, ref.instance)
    assert fast.semantic.shape == (40, 48) and fast.semantic.dtype == torch.int64
    if min_alpha < 1.0:
        assert (fast.semantic != IGNORE_LABEL).any() and (fast.instance != IGNORE_LABEL).any()


@pytest.mark.parametrize("seed", range(3))
def test_walk_vote_with_ties_and_all_ignore(seed):
    scene = random_scene(120, 40 + seed)
    scene["opacity_logits"][:] = 4.0  # equal opacities: many equal weights between labels
    semantic, instance = labels_of(120, seed, classes=2, ignore_share=0.5)
    fast, ref = both(scene, semantic, instance, 2, 3, 0.5)
    assert torch.equal(fast.semantic, ref.semantic) and torch.equal(fast.instance, ref.instance)
    ignore = torch.full((120,), IGNORE_LABEL)
    fast, ref = both(scene, ignore, ignore, 2, 3, 0.5)
    assert (fast.semantic == IGNORE_LABEL).all() and torch.equal(fast.instance, ref.instance)


def test_no_gaussian_in_view_and_no_gaussian_at_all():
    scene = random_scene(30, 3)
    scene["means"] = scene["means"] + torch.tensor([0.0, -10.0, 0.0])  # behind the camera at y = -3
    semantic, instance = labels_of(30, 3)
    fast, ref = both(scene, semantic, instance, 4, 4, 0.5)
    assert (fast.semantic == IGNORE_LABEL).all() and torch.equal(fast.semantic, ref.semantic)
    empty = {k: v[:0] for k, v in scene.items()}
    fast, _ = both(empty, semantic[:0], instance[:0], 4, 4, 0.5)
    assert (fast.semantic == IGNORE_LABEL).all() and (fast.instance == IGNORE_LABEL).all()


def test_bad_labels_and_options_are_refused():
    scene = random_scene(10, 5)
    semantic, instance = labels_of(10, 5)
    viewmat, K = camera()
    geometry = [scene[k] for k in GEOMETRY]
    with pytest.raises(ValueError, match="outside 0..3"):
        render_label_images(*geometry, viewmat, K, WIDTH, HEIGHT, torch.full((10,), 9), instance, 4)
    with pytest.raises(ValueError, match="9 labels for 10 Gaussians"):
        render_label_images(*geometry, viewmat, K, WIDTH, HEIGHT, semantic[:9], instance[:9], 4)
    with pytest.raises(ValueError, match="top_k"):
        render_label_images(*geometry, viewmat, K, WIDTH, HEIGHT, semantic, instance, 4, top_k=0)
    with pytest.raises(ValueError, match="backend"):
        render_label_images(*geometry, viewmat, K, WIDTH, HEIGHT, semantic, instance, 4, backend="gpu")
