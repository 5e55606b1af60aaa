"""Slow, obviously-correct references for the sparse convolutions and the trilinear devoxelization (tests,
benchmarks).

Dense: scatter the sparse features into a ``[B, C, X, Y, Z]`` grid, run ``torch.nn.functional.conv3d``
/ ``conv_transpose3d``, and read the result back at the output sites. Naive: kernel maps from a
Python dict, one site at a time.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ovgaussian.sparse.kernel_map import kernel_offsets
from ovgaussian.sparse.voxelize import VoxelSites


def scatter_to_dense(features: Tensor, sites: VoxelSites, spatial_shape: tuple[int, int, int], num_scenes: int) -> Tensor:
    """``[B, C, X, Y, Z]`` grid holding ``features [M, C]`` at the sites (zeros elsewhere); differentiable."""
    if len(sites) and (int(sites.coords.min()) < 0 or any(int(sites.coords[:, i].max()) >= spatial_shape[i] for i in range(3))):
        raise ValueError("sites fall outside the dense grid")
    c = features.shape[1]
    flat = features.new_zeros(num_scenes * spatial_shape[0] * spatial_shape[1] * spatial_shape[2], c)
    x, y, z = sites.coords.unbind(1)
    rows = ((sites.batch_index * spatial_shape[0] + x) * spatial_shape[1] + y) * spatial_shape[2] + z
    flat = flat.index_add(0, rows, features)
    return flat.reshape(num_scenes, *spatial_shape, c).permute(0, 4, 1, 2, 3)


def gather_from_dense(grid: Tensor, sites: VoxelSites) -> Tensor:
    """``[M, C]`` values of a ``[B, C, X, Y, Z]`` grid at the sites."""
    x, y, z = sites.coords.unbind(1)
    return grid.permute(0, 2, 3, 4, 1)[sites.batch_index, x, y, z]


def dense_weight(weight: Tensor, kernel_size: int) -> Tensor:
    """``[K, C_in, C_out]`` sparse weight -> ``[C_out, C_in, k, k, k]`` ``conv3d`` weight."""
    k = kernel_size
    return weight.reshape(k, k, k, weight.shape[1], weight.shape[2]).permute(4, 3, 0, 1, 2)


def dense_transposed_weight(weight: Tensor) -> Tensor:
    """``[8, C_in, C_out]`` sparse weight -> ``[C_in, C_out, 2, 2, 2]`` ``conv_transpose3d`` weight."""
    return weight.reshape(2, 2, 2, weight.shape[1], weight.shape[2]).permute(3, 4, 0, 1, 2)


def submanifold_conv_dense(features, sites, weight, kernel_size, spatial_shape, num_scenes) -> Tensor:
    """Dense ``conv3d`` (padding ``k // 2``) read at the input sites."""
    grid = scatter_to_dense(features, sites, spatial_shape, num_scenes)
    out = F.conv3d(grid, dense_weight(weight, kernel_size), padding=kernel_size // 2)
    return gather_from_dense(out, sites)


def down_conv_dense(features, sites, coarse_sites, weight, spatial_shape, num_scenes) -> Tensor:
    """Dense ``conv3d(kernel 2, stride 2)`` read at the coarse sites (``spatial_shape`` even)."""
    grid = scatter_to_dense(features, sites, spatial_shape, num_scenes)
    return gather_from_dense(F.conv3d(grid, dense_weight(weight, 2), stride=2), coarse_sites)


def up_conv_dense(features, coarse_sites, fine_sites, weight, coarse_shape, num_scenes) -> Tensor:
    """Dense ``conv_transpose3d(kernel 2, stride 2)`` read at the fine sites."""
    grid = scatter_to_dense(features, coarse_sites, coarse_shape, num_scenes)
    return gather_from_dense(F.conv_transpose3d(grid, dense_transposed_weight(weight), stride=2), fine_sites)


def naive_submanifold_pairs(sites: VoxelSites, kernel_size: int) -> set[tuple[int, int, int]]:
    """All ``(offset_index, in_row, out_row)`` triples of a submanifold conv, from a Python dict."""
    table = {(int(b), *map(int, c)): i for i, (b, c) in enumerate(zip(sites.batch_index, sites.coords))}
    pairs = set()
    for (b, x, y, z), out_row in table.items():
        for k, (dx, dy, dz) in enumerate(kernel_offsets(kernel_size)):
            in_row = table.get((b, x + dx, y + dy, z + dz))
            if in_row is not None:
                pairs.add((k, in_row, out_row))
    return pairs


def trilinear_gather_reference(
    voxel_coords: Tensor,  # [M, 3] int coordinates of the occupied voxels
    voxel_batch: Tensor,  # [M] scene of each voxel
    points: Tensor,  # [N, 3] positions
    point_batch: Tensor,  # [N] scene of each point
    voxel_size: Tensor,  # [B] voxel edge per scene
    origin: Tensor,  # [B, 3] corner of voxel (0, 0, 0) per scene
) -> Tensor:  # [N, M] float64 weights
    """Slow, obviously-correct trilinear weights, as a dense ``[N, M]`` matrix: for each point, every occupied voxel
    whose centre lies within one voxel edge on each axis gets the product of ``1 - |distance| / edge`` over the axes;
    each row is normalized to sum to 1. Written from positions, not from the offsets that
    :func:`ovgaussian.sparse.devoxelize.trilinear_gather` uses."""
    n, m = points.shape[0], voxel_coords.shape[0]
    # Plain Python floats: the same arithmetic as on tensor scalars, without their per-element overhead.
    point_rows, voxel_rows = points.double().tolist(), voxel_coords.tolist()
    point_scenes, voxel_scenes = point_batch.tolist(), voxel_batch.tolist()
    edges, corners = voxel_size.double().tolist(), origin.double().tolist()
    out = torch.zeros(n, m, dtype=torch.float64)
    for i in range(n):
        b = point_scenes[i]
        edge = edges[b]
        weights = [0.0] * m
        for j in range(m):
            if voxel_scenes[j] != b:
                continue
            centre = [corners[b][a] + (voxel_rows[j][a] + 0.5) * edge for a in range(3)]
            gap = [abs(point_rows[i][a] - centre[a]) / edge for a in range(3)]
            if all(g < 1.0 for g in gap):
                weights[j] = (1.0 - gap[0]) * (1.0 - gap[1]) * (1.0 - gap[2])
        total = sum(weights)
        out[i] = torch.tensor([w / total for w in weights], dtype=torch.float64)
    return out
