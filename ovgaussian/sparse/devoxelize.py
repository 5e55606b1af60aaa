"""Voxel features back to points: the nearest voxel, or trilinear interpolation between voxel centres.

A point's *nearest* feature is its own voxel's row. Its *trilinear* feature blends the up to 8 occupied voxels whose
centres surround it (the point-voxel devoxelization of SPVCNN, Tang et al. 2020): along each axis the point lies
between its own voxel's centre and the next centre on its side, at fraction ``t`` of a voxel edge, and the corner
weights are the products of ``1 - t`` and ``t``. Corners that are not occupied are dropped and the weights of the
others renormalized to sum to 1. The own voxel's weight is at least 1/8 (``t <= 1/2`` from its centre on every
axis), so the renormalization is always defined, and a point at its voxel's centre gets exactly the nearest feature.
Two points of one voxel then get different features where their neighbourhoods differ (a wall Gaussian beside a door
voxel leans towards the door's features), which the nearest voxel cannot express.

Both are one :class:`PointGather`: ``rows [N, K]`` voxel rows and ``weights [N, K]`` (``K = 1``, weight 1, for the
nearest voxel; ``K = 8`` for trilinear, dropped corners pointing at the own voxel with weight 0). ``gather`` applies
it, ``scatter`` is its transpose (the gradient with respect to the voxel features). On CPU the trilinear corners,
the blend and its transpose are serial numba loops (``_numba_kernels``); the torch loops over the ``K`` columns
(``gather_reference``, ``scatter_reference``, and the GPU path) and the dense ``trilinear_gather_reference`` of
``ovgaussian.sparse.reference`` are what the tests compare them with. ``benchmarks/bench_devoxelize.py`` times both.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ovgaussian.sparse import _numba_kernels as nk
from ovgaussian.sparse.voxelize import VoxelSites


class PointGather(NamedTuple):
    """Per-point blend of voxel rows: ``point i = sum_k weights[i, k] * features[rows[i, k]]``.

    Attributes:
        rows: ``[N, K]`` int64 voxel rows.
        weights: ``[N, K]`` float32 weights, each row summing to 1.
    """

    rows: Tensor
    weights: Tensor

    @classmethod
    def nearest(cls, point_to_voxel: Tensor) -> "PointGather":
        """Each point takes its own voxel's row (``point_to_voxel [N]``)."""
        rows = point_to_voxel.long().reshape(-1, 1)
        return cls(rows, torch.ones(rows.shape, dtype=torch.float32, device=rows.device))

    def take(self, points: Tensor) -> "PointGather":
        """The gather of the points ``points [R]`` (int64 rows, any order)."""
        return PointGather(self.rows[points], self.weights[points])

    def slice(self, start: int, end: int) -> "PointGather":
        """The gather of points ``start .. end - 1``."""
        return PointGather(self.rows[start:end], self.weights[start:end])

    def gather(self, features: Tensor) -> Tensor:  # [M, C] -> [N, C]
        """Point features from voxel features (differentiable in ``features``)."""
        if self.rows.shape[1] == 1:
            return features[self.rows[:, 0]]
        if features.device.type != "cpu":
            return self.gather_reference(features)
        return _Blend.apply(features, self.rows, self.weights)

    def scatter(self, point_grads: Tensor, num_voxels: int) -> Tensor:  # [N, C] -> [M, C]
        """The transpose of :meth:`gather`: ``[num_voxels, C]`` sums of the point rows' shares."""
        if self.rows.shape[1] == 1:
            return point_grads.new_zeros(num_voxels, point_grads.shape[1]).index_add_(0, self.rows[:, 0], point_grads)
        if point_grads.device.type != "cpu":
            return self.scatter_reference(point_grads, num_voxels)
        out = point_grads.new_zeros(num_voxels, point_grads.shape[1])
        nk.blend_scatter(out.numpy(), self.rows.contiguous().numpy(),
                         self.weights.to(point_grads.dtype).contiguous().numpy(),
                         point_grads.detach().contiguous().numpy())
        return out

    def gather_reference(self, features: Tensor) -> Tensor:
        """:meth:`gather` as a torch loop over the ``K`` columns (autograd's own backward)."""
        out = features[self.rows[:, 0]] * self.weights[:, :1].to(features.dtype)
        for k in range(1, self.rows.shape[1]):
            out = out + features[self.rows[:, k]] * self.weights[:, k:k + 1].to(features.dtype)
        return out

    def scatter_reference(self, point_grads: Tensor, num_voxels: int) -> Tensor:
        """:meth:`scatter` as a torch loop of index-adds over the ``K`` columns."""
        out = point_grads.new_zeros(num_voxels, point_grads.shape[1])
        for k in range(self.rows.shape[1]):
            out.index_add_(0, self.rows[:, k], point_grads * self.weights[:, k:k + 1].to(point_grads.dtype))
        return out


class _Blend(torch.autograd.Function):
    """``PointGather.gather`` on CPU: the numba blend forward, its transpose backward (no gradient to rows or
    weights, which are not learned)."""

    @staticmethod
    def forward(ctx, features, rows, weights):  # noqa: D102
        rows, weights = rows.contiguous(), weights.to(features.dtype).contiguous()
        out = features.new_empty(rows.shape[0], features.shape[1])
        nk.blend_rows(features.detach().contiguous().numpy(), rows.numpy(), weights.numpy(), out.numpy())
        ctx.save_for_backward(rows, weights)
        ctx.num_voxels = features.shape[0]
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        if not ctx.needs_input_grad[0]:
            return None, None, None
        return PointGather(*ctx.saved_tensors).scatter(grad_out, ctx.num_voxels), None, None


def neighbour_table(sites: VoxelSites) -> Tensor:  # [M, 27] int64
    """Row of the site at each offset ``(dx, dy, dz)`` in ``{-1, 0, 1}^3`` (lexicographic, ``kernel_offsets(3)``)
    from each site, or -1: read off the sites' cached 3^3 submanifold kernel map, which the backbone's convolutions
    on these sites build anyway."""
    kmap = sites.submanifold_map(3)
    table = torch.full((len(sites), kmap.kernel_volume), -1, dtype=torch.int64, device=sites.keys.device)
    for k, (rows_in, rows_out) in enumerate(zip(kmap.in_indices, kmap.out_indices)):
        table[rows_out, k] = rows_in
    return table


def trilinear_gather(
    sites: VoxelSites,  # the occupied voxels
    point_to_voxel: Tensor,  # [N] row of each point's voxel
    offsets: Tensor,  # [N, 3] position inside its voxel in voxel edges, [0, 1]
) -> PointGather:
    """The trilinear :class:`PointGather` of points at ``offsets`` inside their voxels (module docstring).

    ``offsets`` are ``(p - voxel corner) / voxel edge``; the voxel centre is at 0.5. Along an axis a point below the
    centre blends with the voxel at ``-1``, one above it with ``+1``, with weight ``|offset - 0.5|`` for the
    neighbour and ``1 - |offset - 0.5|`` for its own voxel. Computed on CPU (numba) and moved to the inputs' device.
    """
    n = point_to_voxel.shape[0]
    if offsets.shape != (n, 3):
        raise ValueError(f"offsets must be [{n}, 3], got {tuple(offsets.shape)}")
    device = point_to_voxel.device
    rows = np.empty((n, 8), np.int64)
    weights = np.empty((n, 8), np.float32)
    table = neighbour_table(sites).cpu().contiguous().numpy()
    nk.trilinear_corners(table, point_to_voxel.long().cpu().contiguous().numpy(), offsets.cpu().contiguous().numpy(),
                         rows, weights)
    return PointGather(torch.from_numpy(rows).to(device), torch.from_numpy(weights).to(device))
