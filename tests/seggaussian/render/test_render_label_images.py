"""Label images voted inside the walk (``render_label_images``) against the two steps: blend weights, then the vote."""

from __future__ import annotations

import numpy as np
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


def surfaces(num, seed, opacity_logit):
    """Gaussians on two parallel planes facing the camera at y = -0.3 and y = 0.4 (flat, overlapping), labelled by
    region: the front plane's left and right halves and the back plane, each one class and one instance, with a few
    Gaussians of other labels mixed in; so most pixels see one label a few Gaussians deep."""
    g = torch.Generator().manual_seed(seed)
    front = torch.rand(num, generator=g) < 0.6
    means = torch.rand(num, 3, generator=g) * 2.0 - 1.0
    means[:, 1] = torch.where(front, -0.3, 0.4) + torch.randn(num, generator=g) * 0.01
    log_scales = torch.stack([torch.full((num,), -2.3), torch.full((num,), -5.0), torch.full((num,), -2.3)], 1)
    log_scales = log_scales + torch.randn(num, 3, generator=g) * 0.2
    semantic = torch.where(front, (means[:, 0] > 0).long(), torch.full((num,), 2))
    instance = semantic * 10 + 1
    stray = torch.rand(num, generator=g) < 0.03
    semantic[stray] = 3
    instance[torch.rand(num, generator=g) < 0.02] = IGNORE_LABEL
    opacity = torch.full((num,), float(opacity_logit)) + torch.randn(num, generator=g) * 0.5
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(num, 1)
    return {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": opacity}, semantic, instance


@pytest.mark.parametrize("opacity_logit", [-2.0, 0.0, 3.0])
@pytest.mark.parametrize("min_alpha", [0.1, 0.5, 0.95])
def test_walk_vote_stops_inside_one_label_as_the_reference(opacity_logit, min_alpha):
    # coherent labels: most pixels stop once one label's slots outweigh all that can follow (the early stop on one
    # label), boundaries and strays take the full-slots rule; faint Gaussians (-2.0) settle deep, dense ones at once
    scene, semantic, instance = surfaces(1500, 5, opacity_logit)
    fast, ref = both(scene, semantic, instance, 4, 16, min_alpha, 64, 48)
    assert torch.equal(fast.semantic, ref.semantic) and torch.equal(fast.instance, ref.instance)
    assert len(torch.unique(fast.semantic)) >= 3


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


@pytest.mark.parametrize("seed", range(4))
def test_screen_candidates_hold_every_gaussian_the_projection_keeps(seed):
    """Gaussians all around the camera (behind it, at the near plane, just beside the image, far beyond the Jacobian's
    clamp), small to huge and needle-like: every one the projection keeps is a candidate, most others are not."""
    from seggaussian.render.projection_numba import project_gaussians_fast
    from seggaussian.render.screen_cull import largest_scales, screen_candidates

    g = torch.Generator().manual_seed(seed)
    n = 20_000
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 4.0
    means[: n // 10, 1] = -3.0 + 0.01 + torch.rand(n // 10, generator=g, dtype=torch.float64) * 1e-3  # at the near plane
    log_scales = torch.randn(n, 3, generator=g, dtype=torch.float64) * 1.5 - 2.5
    log_scales[::7, 0] += 4.0  # needles
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    width, height = (64, 48) if seed % 2 else (160, 90)
    viewmat, K = camera(width, height)
    projection = project_gaussians_fast(means, quats, log_scales, viewmat, K, width, height)
    box = projection.pixel_box
    kept = projection.valid & (box[:, 0] <= box[:, 2]) & (box[:, 1] <= box[:, 3])
    rows = screen_candidates(means.numpy(), largest_scales(log_scales.numpy()), viewmat.numpy(), K.numpy(), width,
                             height)
    assert np.all(np.diff(rows) > 0)
    candidate = np.zeros(n, bool)
    candidate[rows] = True
    assert not (kept.numpy() & ~candidate).any()
    assert kept.sum() > 100 and candidate.mean() < 0.7  # behind and beside the camera: culled


def test_label_scene_renders_many_views_as_the_reference():
    from seggaussian.render.label_images import prepare_label_scene, render_label_scene

    scene = random_scene(300, 11, spread=1.5)
    scene["log_scales"][::5] += 2.0  # some large Gaussians reaching in from beside the image
    semantic, instance = labels_of(300, 11)
    prepared = prepare_label_scene(*(scene[k] for k in GEOMETRY), semantic, instance, 4)
    for eye in ((0.3, -3.0, 0.6), (2.5, 0.5, 0.4), (0.1, 0.2, 3.0)):
        viewmat, K = camera(40, 30, eye)
        fast = render_label_scene(prepared, viewmat, K, 40, 30, 4, 0.5)
        ref = render_label_images(*(scene[k] for k in GEOMETRY), viewmat, K, 40, 30, semantic, instance, 4, 4, 0.5,
                                  backend="reference")
        assert torch.equal(fast.semantic, ref.semantic) and torch.equal(fast.instance, ref.instance)
        assert (fast.semantic != IGNORE_LABEL).any()
