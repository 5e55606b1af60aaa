"""The voxel geometry inputs (``OVGaussianNetConfig.voxel_geometry``): each voxel's centre offset and covariance
against a per-voxel loop, a plane's zero variance along its normal, and the backbone's input width."""

import json

import numpy as np
import pytest
import torch

from ovgaussian.model.config import OVGaussianNetConfig
from ovgaussian.model.network import OVGaussianNet
from ovgaussian.run.checkpoint import saved_model_config
from ovgaussian.run.config import config_to_dict
from ovgaussian.sparse import voxel_geometry_features, voxelize_points


def reference_geometry(offsets: np.ndarray, voxel: np.ndarray, num: int, weights: np.ndarray) -> np.ndarray:
    """Per voxel, the weighted mean and covariance of ``offsets - 0.5`` by plain loops."""
    out = np.zeros((num, 9))
    pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    for v in range(num):
        rows = np.flatnonzero(voxel == v)
        u, w = offsets[rows].astype(np.float64) - 0.5, weights[rows].astype(np.float64)
        mean = (u * w[:, None]).sum(0) / w.sum()
        d = u - mean
        cov = [(w * d[:, a] * d[:, b]).sum() / w.sum() for a, b in pairs]
        out[v] = np.concatenate([2 * mean, 12 * np.array(cov)])
    return out


@pytest.mark.parametrize("weighted", [False, True])
def test_geometry_features_follow_the_loop_with_single_point_voxels(weighted):
    g = torch.Generator().manual_seed(3)
    points = torch.rand(400, 3, generator=g) * 0.6
    points[-1] = torch.tensor([5.0, 5.0, 5.0])  # alone in its voxel: covariance 0
    weights = torch.rand(400, generator=g) + 0.01 if weighted else None
    vox = voxelize_points(points, torch.zeros(400, 1), torch.zeros(400, dtype=torch.int64), 0.1, 4096, weights=weights)
    m = len(vox.voxels.sites)
    got = voxel_geometry_features(vox.point_offsets, vox.point_to_voxel, m, weights).numpy()
    want = reference_geometry(vox.point_offsets.numpy(), vox.point_to_voxel.numpy(), m,
                              np.ones(400) if weights is None else weights.numpy())
    np.testing.assert_allclose(got, want, atol=2e-5)
    alone = int(vox.point_to_voxel[-1])
    assert np.all(got[alone, 3:] == 0) and np.all(np.abs(got[:, :3]) <= 1.0 + 1e-6)


def test_a_plane_through_a_voxel_has_no_variance_along_its_normal():
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(500, 2, generator=g) * 0.0999
    wall = torch.cat([xy[:, :1], torch.full((500, 1), 0.031), xy[:, 1:]], dim=1)  # the plane y = 3.1 cm
    vox = voxelize_points(wall, torch.zeros(500, 1), torch.zeros(500, dtype=torch.int64), 0.1, 4096)
    features = voxel_geometry_features(vox.point_offsets, vox.point_to_voxel, len(vox.voxels.sites))
    assert len(features) == 1
    xx, yy, zz = features[0, 3:6].tolist()
    assert yy == pytest.approx(0.0, abs=1e-5) and xx == pytest.approx(1.0, abs=0.15) and zz == pytest.approx(1.0, abs=0.15)


def test_the_backbone_reads_nine_more_inputs_and_old_runs_load_without_them():
    tiny = dict(widths=(4,) * 8, blocks=(1,) * 8, stem_width=4, stem_kernel_size=3, embedding_width=8, voxel_size=0.1)
    plain, geometric = OVGaussianNetConfig(**tiny), OVGaussianNetConfig(**tiny, voxel_geometry=True)
    assert geometric.backbone_inputs == plain.backbone_inputs + 9 and geometric.num_attributes == plain.num_attributes
    g = torch.Generator().manual_seed(1)
    means = torch.rand(300, 3, generator=g)
    attrs = torch.rand(300, 11, generator=g)
    batch = torch.zeros(300, dtype=torch.int64)
    net = OVGaussianNet(geometric).eval()
    assert net.backbone.stem.conv.in_channels == plain.num_attributes + 9
    with torch.no_grad():
        before = net(means, attrs, batch)
        moved = means.clone()
        moved[:, 2] = torch.floor(moved[:, 2] / 0.1) * 0.1 + 0.05  # same voxels, centres flattened in z
        after = net(moved, attrs, batch)
    assert torch.isfinite(before).all() and not torch.allclose(before, after)  # it reads where the centres lie
    payload = json.loads(json.dumps(config_to_dict(geometric)))
    assert saved_model_config(payload) == geometric
    del payload["voxel_geometry"]
    assert saved_model_config(payload).voxel_geometry is False
