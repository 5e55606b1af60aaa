"""q and -q are the same rotation: the network must see (and predict) the same thing for both, on the
training data path and on the inference path (issue 16)."""

from __future__ import annotations

import numpy as np
import torch

from ovgaussian.data.training_data import TrainingData
from ovgaussian.model.network import canonical_quat_sign, gaussian_attributes
from ovgaussian.data.scene_source import InMemorySource
from ovgaussian.run.config import DataConfig
from ovgaussian.text.vocabulary import training_vocabulary
from seggaussian.core.gaussians import Gaussians
from test_train import make_scene, text_stub, tiny_config, tiny_model_config


def flipped(g: Gaussians, rows: np.ndarray) -> Gaussians:
    """``g`` with the quaternions of ``rows`` negated (geometry unchanged)."""
    quats = g.quats.copy()
    quats[rows] *= -1.0
    return Gaussians.from_arrays(g.means, quats, g.log_scales, g.opacity_logits, g.sh, extras=dict(g.extras))


def random_subset(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random(n) < 0.5


def test_canonical_sign_is_deterministic_including_zero_leading_components():
    q = torch.tensor([[0.5, -0.5, 0.5, 0.5], [-0.5, 0.5, 0.5, 0.5], [0.0, -0.6, 0.8, 0.0], [-0.0, 0.0, 0.0, -1.0],
                      [0.0, 0.0, 0.0, 0.0]])
    c = canonical_quat_sign(q)
    assert torch.equal(c, canonical_quat_sign(-q))
    expected = torch.tensor([[0.5, -0.5, 0.5, 0.5], [0.5, -0.5, -0.5, -0.5], [0.0, 0.6, -0.8, 0.0], [0.0, 0.0, 0.0, 1.0],
                             [0.0, 0.0, 0.0, 0.0]])
    torch.testing.assert_close(c, expected, rtol=0, atol=0)
    g = torch.Generator().manual_seed(3)
    r = torch.randn(1000, 4, generator=g)
    r[::7, 0] = 0.0  # w == 0 exactly: the sign falls to x
    r[::21, 1] = 0.0
    signs = torch.where(torch.rand(1000, 1, generator=g) < 0.5, -1.0, 1.0)
    assert torch.equal(canonical_quat_sign(r), canonical_quat_sign(r * signs))


def test_inference_predictions_are_invariant_under_quaternion_sign():
    """``gaussian_attributes`` (used by predict and bench) and the network's per-Gaussian outputs."""
    from ovgaussian.run.checkpoint import build_network
    from ovgaussian.predict.query import ModelPredictor

    g = make_scene(3).gaussians
    h = flipped(g, random_subset(len(g), 0))
    assert not np.array_equal(g.quats, h.quats)
    assert torch.equal(gaussian_attributes(g), gaussian_attributes(h))
    predictor = ModelPredictor(build_network(tiny_model_config(12)), None)
    a, b = predictor.encode_gaussians(g), predictor.encode_gaussians(h)
    assert np.array_equal(a, b)


def test_training_path_outputs_are_invariant_under_quaternion_sign(tmp_path):
    """Train-mode network (batch statistics) on samples drawn from scenes with flipped signs: the same
    per-Gaussian semantic vectors and the same losses, with and without augmentation."""
    from ovgaussian.run.checkpoint import build_network
    from ovgaussian.train.step_losses import batch_losses, network_inputs

    scenes = [make_scene(s) for s in (0, 1)]
    other = [r._replace(gaussians=flipped(r.gaussians, random_subset(len(r.gaussians), 7 + i)))
             for i, r in enumerate(scenes)]
    voc = training_vocabulary(20)
    for augment in (False, True):
        config = DataConfig(blend_top_k=8, pixels_per_view=200, augment=augment)
        outputs = []
        for records in (scenes, other):
            data = TrainingData(InMemorySource(records), config, voc)
            samples = [data.sample(r.scene_id, np.random.default_rng(5)) for r in records]
            net = build_network(tiny_model_config(12)).train()
            semantic = net(*network_inputs(samples, "cpu"))
            terms = batch_losses(net, samples, text_stub(), tiny_config(tmp_path, 1), False, "cpu")
            outputs.append((semantic.detach(), [float(t.total.detach()) for t in terms]))
        assert torch.equal(outputs[0][0], outputs[1][0]), augment
        assert outputs[0][1] == outputs[1][1]
