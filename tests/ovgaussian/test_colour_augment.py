"""The colour augment (``DataConfig.colour_augment``): one hue turn, saturation and gain for a whole scene.

Checked against the colour-by-colour reference (Rodrigues' formula on each colour's chroma), on the colours whose
images are known (primaries turn into each other, greys stay grey), and in the trainer's data path: only the
colours change, all by one linear map of RGB, and only when asked.
"""

from __future__ import annotations

import numpy as np
import pytest

from ovgaussian.data.augmentation import colour_matrix, recolour, recolour_reference
from seggaussian.core.constants import SH_C0


def test_the_matrix_is_the_reference_on_random_colours_and_draws():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(-0.2, 1.2, (200, 3))
    for turn, saturation, gain in [(0.0, 1.0, 1.0), (np.pi, 0.5, 1.2), (-2.0, 1.5, 0.8), (0.3, 0.0, 1.0)]:
        fast = rgb @ colour_matrix(turn, saturation, gain).T
        np.testing.assert_allclose(fast, recolour_reference(rgb, turn, saturation, gain), atol=1e-12)
    np.testing.assert_allclose(colour_matrix(0.0, 1.0, 1.0), np.eye(3), atol=1e-15)


def test_primaries_turn_into_each_other_and_greys_stay_grey():
    third = 2.0 * np.pi / 3.0
    primaries = np.eye(3)
    turned = primaries @ colour_matrix(third, 1.0, 1.0).T
    np.testing.assert_allclose(turned, np.roll(primaries, 1, axis=1), atol=1e-12)  # red -> green -> blue -> red
    greys = np.linspace(0.0, 1.0, 5)[:, None] * np.ones(3)
    for turn in (0.7, -2.5):
        np.testing.assert_allclose(greys @ colour_matrix(turn, 0.6, 1.1).T, 1.1 * greys, atol=1e-12)
    # saturation 0: every colour becomes its own grey (the channels' mean), times the gain
    rgb = np.random.default_rng(1).uniform(0.0, 1.0, (50, 3))
    np.testing.assert_allclose(rgb @ colour_matrix(1.0, 0.0, 0.9).T, 0.9 * rgb.mean(axis=1, keepdims=True) * np.ones(3),
                               atol=1e-12)


def test_recolour_maps_every_colour_of_a_scene_by_one_matrix():
    rng = np.random.default_rng(2)
    sh_dc = rng.normal(0.0, 0.8, (300, 3)).astype(np.float32)
    out = recolour(np.random.default_rng(5), sh_dc)
    assert out.shape == sh_dc.shape and out.dtype == np.float32 and np.isfinite(out).all()
    rgb, new = 0.5 + SH_C0 * sh_dc.astype(np.float64), 0.5 + SH_C0 * out.astype(np.float64)
    matrix, *_ = np.linalg.lstsq(rgb, new, rcond=None)
    np.testing.assert_allclose(rgb @ matrix, new, atol=1e-5)
    assert not np.allclose(matrix, np.eye(3), atol=1e-2)  # a draw that moved the palette
    np.testing.assert_array_equal(recolour(np.random.default_rng(5), sh_dc), out)  # seeded
    assert recolour(np.random.default_rng(5), sh_dc[:0]).shape == (0, 3)


@pytest.mark.parametrize("flag", [False, True])
def test_the_training_data_recolours_only_when_asked(flag):
    """With the flag, some samples' colours move, each by one linear map of RGB, and nothing else of the sample moves
    (same Gaussians, labels, pixels); without it every sample's colours are the stored ones."""
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.data.training_data import TrainingData
    from ovgaussian.run.config import DataConfig
    from ovgaussian.text.vocabulary import training_vocabulary
    from test_train import make_scene

    scene = make_scene(0)
    plain = TrainingData(InMemorySource([scene]), DataConfig(pixels_per_view=64), training_vocabulary(20))
    data = TrainingData(InMemorySource([scene]), DataConfig(colour_augment=flag, pixels_per_view=64),
                        training_vocabulary(20))
    moved = 0
    for seed in range(10):
        a = plain.sample(scene.scene_id, np.random.default_rng(seed))
        b = data.sample(scene.scene_id, np.random.default_rng(seed))
        for field in ("means", "quats", "log_scales", "opacity_logits", "labels", "pixels", "pixel_ids"):
            np.testing.assert_array_equal(getattr(a, field).numpy(), getattr(b, field).numpy())
        before = 0.5 + SH_C0 * a.sh_dc.numpy().astype(np.float64)
        after = 0.5 + SH_C0 * b.sh_dc.numpy().astype(np.float64)
        if np.array_equal(before, after):
            continue
        moved += 1
        matrix, *_ = np.linalg.lstsq(before, after, rcond=None)
        np.testing.assert_allclose(before @ matrix, after, atol=1e-5)
    assert (moved > 0) if flag else (moved == 0)
