"""The network's inputs for fitted splats: robust encoding, opacity-weighted voxel pooling, old runs unchanged."""

from __future__ import annotations

import json

import pytest
import torch

from ovgaussian.run.checkpoint import saved_model_config
from ovgaussian.model.network import (
    ROBUST_COORD_CLIP, ROBUST_LOG_SCALE_RANGE, OVGaussianNet, encode_attributes, normalized_coordinates,
    robust_coordinates,
)
from ovgaussian.model.config import OVGaussianNetConfig
from ovgaussian.sparse import voxelize_points
from ovgaussian.run.config import config_to_dict

TINY = dict(widths=(4, 4, 8, 8, 8, 8, 4, 4), blocks=(1, 1, 1, 1, 1, 1, 1, 1), stem_width=4, stem_kernel_size=3,
            embedding_width=12, voxel_size=0.1)


def room(seed: int, n: int = 3000):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 3.0, 2.5])
    attrs = torch.cat([torch.rand(n, 3, generator=g), torch.rand(n, 1, generator=g),
                       torch.exp(torch.randn(n, 3, generator=g) - 4.0), torch.nn.functional.normalize(
                           torch.randn(n, 4, generator=g), dim=1)], dim=1)
    return means, attrs


def weighted_pool_reference(points, features, voxel_size, weights):
    """One voxel at a time: sum(w f) / sum(w) over the points whose floor((p - min) / size) is that voxel."""
    keys = torch.floor((points.double() - points.double().min(0).values) / voxel_size).long()
    out = {}
    for i in range(points.shape[0]):
        k = tuple(keys[i].tolist())
        acc, total = out.get(k, (torch.zeros(features.shape[1], dtype=torch.float64), 0.0))
        out[k] = (acc + float(weights[i]) * features[i].double(), total + float(weights[i]))
    return {k: acc / total for k, (acc, total) in out.items()}


def test_opacity_weighted_pooling_matches_reference():
    means, attrs = room(0, 400)
    weights = attrs[:, 3].clamp_min(1e-3)
    vox = voxelize_points(means, attrs, torch.zeros(400, dtype=torch.int64), 0.5, 4096, weights=weights)
    expected = weighted_pool_reference(means, attrs, 0.5, weights)
    coords = vox.voxels.sites.coords
    assert len(expected) == coords.shape[0]
    for row in range(coords.shape[0]):
        torch.testing.assert_close(vox.voxels.features[row].double(), expected[tuple(coords[row].tolist())],
                                   rtol=1e-5, atol=1e-6)


def test_pooling_weights_must_be_positive():
    means, attrs = room(1, 10)
    with pytest.raises(ValueError, match="positive"):
        voxelize_points(means, attrs, torch.zeros(10, dtype=torch.int64), 0.5, 4096, weights=torch.zeros(10))


def test_faint_gaussians_barely_move_a_voxel_under_opacity_pooling():
    """One opaque Gaussian and nine transparent ones of another colour in a voxel: the weighted pool stays near the
    opaque colour, the plain mean is dragged to the faint one."""
    means = torch.full((10, 3), 0.05)
    attrs = torch.zeros(10, 11)
    attrs[0, 0] = 1.0  # red, opaque
    attrs[0, 3] = 0.99
    attrs[1:, 2] = 1.0  # blue, nearly transparent
    attrs[1:, 3] = 0.005
    batch = torch.zeros(10, dtype=torch.int64)
    weighted = voxelize_points(means, attrs, batch, 0.1, 4096, weights=attrs[:, 3]).voxels.features[0]
    plain = voxelize_points(means, attrs, batch, 0.1, 4096).voxels.features[0]
    assert weighted[0] > 0.9 and weighted[2] < 0.1
    assert plain[0] < 0.2 and plain[2] > 0.8


def test_robust_coordinates_ignore_far_floaters():
    """A room plus 1 % floaters 50 m away: the room's robust coordinates barely move; the bounding-box ones shrink
    to nothing."""
    means, _ = room(2)
    batch = torch.zeros(means.shape[0], dtype=torch.int64)
    floaters = torch.tensor([50.0, -40.0, 30.0]) + torch.rand(20, 3, generator=torch.Generator().manual_seed(3))
    with_floaters = torch.cat([means, floaters])
    batch2 = torch.zeros(with_floaters.shape[0], dtype=torch.int64)
    clean = robust_coordinates(means, batch)
    noisy = robust_coordinates(with_floaters, batch2)[: means.shape[0]]
    assert (clean - noisy).abs().max() < 0.05
    assert noisy.abs().max() <= ROBUST_COORD_CLIP
    bbox_noisy = normalized_coordinates(with_floaters, batch2)[: means.shape[0]]
    assert (bbox_noisy.amax(0) - bbox_noisy.amin(0)).max() < 0.2  # squeezed to a tenth: what robust avoids


def test_robust_coordinates_per_scene_and_translation_invariant():
    means_a, _ = room(4, 500)
    means_b, _ = room(5, 700)
    batch = torch.cat([torch.zeros(500, dtype=torch.int64), torch.ones(700, dtype=torch.int64)])
    both = robust_coordinates(torch.cat([means_a, means_b + 100.0]), batch)
    torch.testing.assert_close(both[:500], robust_coordinates(means_a, torch.zeros(500, dtype=torch.int64)))
    torch.testing.assert_close(both[500:], robust_coordinates(means_b, torch.zeros(700, dtype=torch.int64)),
                               atol=1e-4, rtol=1e-4)


def test_encode_attributes_clips_heavy_tails():
    attrs = torch.zeros(3, 11)
    attrs[:, 0:3] = torch.tensor([[-0.5, 0.5, 1.7], [0.2, 0.3, 0.4], [2.0, -1.0, 0.0]])
    attrs[:, 4:7] = torch.tensor([[1e-9, 1e-9, 1e-9], [0.1, 0.1, 0.1], [50.0, 50.0, 50.0]])
    attrs[:, 7] = 1.0
    enc = encode_attributes(attrs, 0.1)
    assert enc[:, 0:3].min() >= 0 and enc[:, 0:3].max() <= 1
    low, high = ROBUST_LOG_SCALE_RANGE
    torch.testing.assert_close(enc[:, 4], torch.tensor([low / 2, 0.0, high / 2]))
    assert torch.isfinite(enc).all()


def test_robust_network_output_is_stable_under_floaters():
    """The robust network's output on the room's Gaussians changes little when far floaters are added (their
    voxels are elsewhere; coordinates do not move); the raw encoding's changes a lot."""
    means, attrs = room(6)
    g = torch.Generator().manual_seed(7)
    floaters = torch.tensor([30.0, 30.0, 30.0]) + torch.rand(30, 3, generator=g)
    fattrs = attrs[:30].clone()
    fattrs[:, 4:7] = 5.0  # huge
    changes = {}
    for encoding in ("raw", "robust"):
        net = OVGaussianNet(OVGaussianNetConfig(**TINY, use_coordinates=True, input_encoding=encoding)).eval()
        batch = torch.zeros(means.shape[0], dtype=torch.int64)
        with torch.no_grad():
            clean = net(means, attrs, batch)
            noisy = net(torch.cat([means, floaters]), torch.cat([attrs, fattrs]),
                        torch.zeros(means.shape[0] + 30, dtype=torch.int64))[: means.shape[0]]
        changes[encoding] = float((clean - noisy).norm(dim=1).mean() / clean.norm(dim=1).mean())
    assert changes["robust"] < 0.1
    assert changes["raw"] > 2 * changes["robust"]


def test_runs_saved_before_the_switches_load_with_the_old_behaviour():
    new = OVGaussianNetConfig(**TINY)
    payload = json.loads(json.dumps(config_to_dict(new)))
    assert saved_model_config(payload) == new  # today's run: as saved
    del payload["input_encoding"], payload["pool_weighting"]
    old = saved_model_config(payload)
    assert old.input_encoding == "raw" and old.pool_weighting == "mean"
