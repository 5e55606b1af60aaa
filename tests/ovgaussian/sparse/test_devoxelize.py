"""Voxel features back to Gaussians: the trilinear gather against a dense reference written from positions."""

from __future__ import annotations

import pytest
import torch

from ovgaussian.sparse import VoxelSites, voxelize_points
from ovgaussian.sparse.devoxelize import PointGather, trilinear_gather
from ovgaussian.sparse.reference import trilinear_gather_reference


def dense_weights(point_gather: PointGather, num_voxels: int) -> torch.Tensor:
    """``[N, M]`` float64 matrix of a gather (repeated rows add up)."""
    n = point_gather.rows.shape[0]
    out = torch.zeros(n, num_voxels, dtype=torch.float64)
    for k in range(point_gather.rows.shape[1]):
        out.index_put_((torch.arange(n), point_gather.rows[:, k]), point_gather.weights[:, k].double(), accumulate=True)
    return out


def gather_and_reference(points, batch_index, voxel_size=0.1, max_grid_extent=4096):
    vox = voxelize_points(points, torch.zeros(points.shape[0], 1), batch_index, voxel_size, max_grid_extent)
    sites = vox.voxels.sites
    got = trilinear_gather(sites, vox.point_to_voxel, vox.point_offsets)
    want = trilinear_gather_reference(sites.coords, sites.batch_index, points, batch_index, vox.voxel_size, vox.origin)
    return vox, got, want


def clustered_points(seed: int, n: int, scenes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Points on a few planes and in a few clumps (sparse, partly-occupied neighbourhoods), several scenes far apart."""
    g = torch.Generator().manual_seed(seed)
    batch_index = torch.randint(0, scenes, (n,), generator=g).sort().values
    pts = torch.rand(n, 3, generator=g) * 0.8
    plane = torch.rand(n, generator=g) < 0.5
    pts[plane, 2] = 0.33  # a wall: one layer of voxels in z
    pts += batch_index[:, None].float() * 7.0
    return pts, batch_index


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trilinear_gather_equals_the_dense_reference(seed):
    points, batch_index = clustered_points(seed, 240, 3)
    vox, got, want = gather_and_reference(points, batch_index)
    torch.testing.assert_close(dense_weights(got, len(vox.voxels.sites)), want, rtol=0, atol=2e-6)
    assert got.rows.shape == (240, 8)
    torch.testing.assert_close(got.weights.sum(1), torch.ones(240))


def test_trilinear_gather_on_a_capped_grid_and_at_centres_and_corners():
    """A scene wider than the grid cap (its voxel edge grows), points exactly at voxel centres (the nearest voxel
    alone) and exactly on voxel corners (eight equal shares where all eight are occupied)."""
    edge = 0.25
    centres = (torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 1], [3, 2, 1]]).double() + 0.5) * edge
    block = torch.stack(torch.meshgrid(*[torch.arange(2.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    corner_fill = (block + 5.5) * edge  # the 8 voxels around the corner (6, 6, 6)
    corner = torch.full((1, 3), 6.0 * edge)
    anchor = torch.zeros(1, 3)  # the scene minimum is the grid's origin
    points = torch.cat([centres, corner_fill, anchor, corner]).float()
    vox, got, want = gather_and_reference(points, torch.zeros(len(points), dtype=torch.int64), voxel_size=edge)
    torch.testing.assert_close(dense_weights(got, len(vox.voxels.sites)), want, rtol=0, atol=2e-6)
    at_centre = dense_weights(got, len(vox.voxels.sites))[:4]
    assert torch.equal(at_centre.max(1).values, torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(got.weights[-1], torch.full((8,), 0.125))
    assert len(set(got.rows[-1].tolist())) == 8

    wide = torch.cat([torch.rand(200, 3) * 3.0, torch.tensor([[40.0, 0.0, 0.0]])])
    vox, got, want = gather_and_reference(wide, torch.zeros(201, dtype=torch.int64), voxel_size=0.05,
                                          max_grid_extent=64)
    assert float(vox.voxel_size[0]) > 0.6  # the cap grew the voxel
    torch.testing.assert_close(dense_weights(got, len(vox.voxels.sites)), want, rtol=0, atol=2e-6)


def test_trilinear_gather_degenerate_inputs():
    """One point (its own voxel, weight 1), an isolated point among others, and no points at all."""
    one = torch.tensor([[0.03, 0.07, 0.02]])
    vox, got, _ = gather_and_reference(one, torch.zeros(1, dtype=torch.int64))
    assert torch.equal(got.rows, torch.zeros(1, 8, dtype=torch.int64))
    torch.testing.assert_close(got.weights.sum(1), torch.ones(1))
    features = torch.randn(1, 4)
    torch.testing.assert_close(got.gather(features), features)

    none = voxelize_points(torch.zeros(0, 3), torch.zeros(0, 2), torch.zeros(0, dtype=torch.int64), 0.1, 4096)
    empty = trilinear_gather(none.voxels.sites, none.point_to_voxel, none.point_offsets)
    assert empty.rows.shape == (0, 8) and empty.gather(torch.zeros(0, 4)).shape == (0, 4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gather_keeps_constants_and_scatter_is_its_transpose(dtype):
    """Weights sum to 1 (a constant feature field stays constant); the numba ``gather`` and its backward equal the
    torch loop (``gather_reference``) and autograd's gradient of it; ``scatter`` equals that gradient and
    ``scatter_reference``; for the trilinear and the nearest gather."""
    points, batch_index = clustered_points(7, 300, 2)
    vox = voxelize_points(points, torch.zeros(300, 1), batch_index, 0.1, 4096)
    m = len(vox.voxels.sites)
    for point_gather in (trilinear_gather(vox.voxels.sites, vox.point_to_voxel, vox.point_offsets),
                         PointGather.nearest(vox.point_to_voxel)):
        torch.testing.assert_close(point_gather.gather(torch.full((m, 3), 2.5)), torch.full((300, 3), 2.5))
        upstream = torch.randn(300, 5, dtype=dtype)
        grads, outputs = [], []
        for gather in (point_gather.gather, point_gather.gather_reference):
            features = torch.randn(m, 5, dtype=dtype, generator=torch.Generator().manual_seed(1)).requires_grad_()
            out = gather(features)
            (out * upstream).sum().backward()
            outputs.append(out.detach())
            grads.append(features.grad)
        tolerance = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(outputs[0], outputs[1], **tolerance)
        torch.testing.assert_close(grads[0], grads[1], **tolerance)
        torch.testing.assert_close(point_gather.scatter(upstream, m), grads[1], **tolerance)
        torch.testing.assert_close(point_gather.scatter_reference(upstream, m), grads[1], **tolerance)
        subset, features = torch.tensor([299, 3, 40]), torch.randn(m, 5, dtype=dtype)
        torch.testing.assert_close(point_gather.take(subset).gather(features), point_gather.gather(features)[subset])


def test_trilinear_gather_refuses_offsets_of_the_wrong_shape():
    with pytest.raises(ValueError, match="offsets must be"):
        trilinear_gather(VoxelSites(torch.tensor([5])), torch.zeros(2, dtype=torch.int64), torch.zeros(2, 2))
