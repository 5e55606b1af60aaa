"""Integer voxel keys, active-site sets and voxelization of points (one concept: which sites exist).

A sparse grid level is a set of active sites ``(batch, x, y, z)``. Each site is packed into one int64
key whose order is lexicographic in ``(batch, x, y, z)``, so a sorted key array doubles as a lookup
table (``torch.searchsorted``) and as a canonical site order. Kernel maps are built from these keys
in ``kernel_map.py`` and cached on the :class:`VoxelSites` object they belong to, so one batch of
scenes builds each map (per stride and kernel size) once per forward pass, and a caller that keeps
the ``VoxelSites`` alive reuses them across passes.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ovgaussian.sparse.kernel_map import KernelMap, build_downsample_map, build_submanifold_map
from ovgaussian.sparse.keys import (  # noqa: F401  (re-exported: the key layout is part of this module's API)
    BATCH_MAX, COORD_BITS, COORD_MAX, COORD_MIN, COORD_OFFSET, KEY_MARGIN, offset_key_delta, pack_keys, unpack_keys,
)


class VoxelSites:
    """The active sites of one grid level for a batch of scenes, with its kernel-map cache.

    Attributes:
        keys: ``[M]`` int64 packed keys, strictly increasing (this is the site order).
        batch_index: ``[M]`` int64 scene index of each site.
        coords: ``[M, 3]`` int64 coordinates in units of this level's voxel.
        stride: voxel edge of this level in units of the finest level's voxel (1, 2, 4, ...).
    """

    def __init__(self, keys: Tensor, stride: int = 1) -> None:
        if keys.ndim != 1 or keys.dtype != torch.int64:
            raise ValueError(f"keys must be a 1D int64 tensor, got {tuple(keys.shape)} {keys.dtype}")
        if keys.numel() > 1 and not bool((keys[1:] > keys[:-1]).all()):
            raise ValueError("keys must be strictly increasing (unique and sorted)")
        self.keys = keys
        self.batch_index, self.coords = unpack_keys(keys)
        self.stride = int(stride)
        # Kernel-map cache: ("sub", kernel_size) -> KernelMap; "down" -> (coarser sites, KernelMap).
        self._cache: dict = {}

    @classmethod
    def from_coords(cls, batch_index: Tensor, coords: Tensor, stride: int = 1) -> tuple["VoxelSites", Tensor]:
        """Unique sites of possibly repeated ``(batch, coords)`` rows, and the ``[M_rows]`` inverse map."""
        keys = pack_keys(batch_index, coords)
        unique_keys, inverse = torch.unique(keys, sorted=True, return_inverse=True)
        return cls(unique_keys, stride), inverse

    def __len__(self) -> int:
        return int(self.keys.numel())

    @property
    def num_scenes(self) -> int:
        return int(self.batch_index.max()) + 1 if len(self) else 0

    def submanifold_map(self, kernel_size: int) -> "KernelMap":
        """Cached kernel map of a submanifold conv (outputs = these sites)."""
        key = ("sub", int(kernel_size))
        if key not in self._cache:
            self._cache[key] = build_submanifold_map(self.keys, int(kernel_size))
        return self._cache[key]

    def downsample(self) -> tuple["VoxelSites", "KernelMap"]:
        """Cached coarser level (``floor(coords / 2)``) and the stride-2, kernel-2 map into it."""
        if "down" not in self._cache:
            coarse_keys, kmap = build_downsample_map(self.batch_index, self.coords)
            self._cache["down"] = (VoxelSites(coarse_keys, self.stride * 2), kmap)
        return self._cache["down"]


class SparseVoxels(NamedTuple):
    """Features on the active sites of one level.

    Attributes:
        features: ``[M, C]`` one row per site, in ``sites`` order.
        sites: the :class:`VoxelSites` the rows belong to.
    """

    features: Tensor
    sites: VoxelSites

    def replace(self, features: Tensor) -> "SparseVoxels":
        """Same sites, new ``[M, C']`` features."""
        if features.shape[0] != len(self.sites):
            raise ValueError(f"{features.shape[0]} feature rows for {len(self.sites)} sites")
        return SparseVoxels(features, self.sites)


class Voxelization(NamedTuple):
    """Points grouped into voxels.

    Attributes:
        voxels: mean-pooled point features on the occupied voxels.
        point_to_voxel: ``[N]`` int64 row of each point's voxel in ``voxels.features``.
        voxel_size: ``[B]`` voxel edge (metres) used for each scene.
        origin: ``[B, 3]`` world position of voxel ``(0, 0, 0)``'s corner for each scene.
        point_offsets: ``[N, 3]`` each point's position inside its voxel, ``(p - voxel corner) / voxel edge`` in
            [0, 1], from the float64 positions the voxel was chosen from (``ovgaussian.sparse.devoxelize``).
    """

    voxels: SparseVoxels
    point_to_voxel: Tensor
    voxel_size: Tensor
    origin: Tensor
    point_offsets: Tensor


def voxelize_points(
    points: Tensor,  # [N, 3] world positions
    features: Tensor,  # [N, C] per-point features (mean-pooled per voxel)
    batch_index: Tensor,  # [N] int scene index, 0..B-1
    voxel_size: float,
    max_grid_extent: int,
    weights: "Tensor | None" = None,  # [N] positive pooling weights; None: plain mean
    lattice: int | None = None,
) -> Voxelization:
    """Voxelize points per scene: ``coords = floor((p - origin) / voxel_size)``.

    ``lattice`` places the grid. None puts the origin at the scene's minimum corner, so one point further out (a
    floater) moves every voxel boundary relative to the rest. An integer ``k`` rounds that corner down to a multiple
    of ``k`` voxels in the points' frame: the voxel boundaries, and those of every coarser level whose stride divides
    ``k`` (a U-Net's strided levels), stay where they are whatever the extreme points are; an outlier only shifts
    the integer coordinates by a multiple of ``k``, which no convolution of those levels sees.

    The voxel size of a scene grows beyond ``voxel_size`` only when the scene would span more than
    ``max_grid_extent`` voxels along some axis; it is then ``extent / (max_grid_extent - 1)`` so that
    the grid fits (the adaptive cap, reported in ``Voxelization.voxel_size``).
    Features are mean-pooled per voxel (differentiable in ``features``), or weighted-mean pooled with
    ``weights`` (each > 0; not differentiated).
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got {tuple(points.shape)}")
    n = points.shape[0]
    if features.shape[0] != n or batch_index.shape != (n,):
        raise ValueError(
            f"features {tuple(features.shape)} and batch_index {tuple(batch_index.shape)} must have {n} rows"
        )
    if not (voxel_size > 0):
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    if not 1 <= max_grid_extent <= COORD_MAX:
        raise ValueError(f"max_grid_extent must be in [1, {COORD_MAX}], got {max_grid_extent}")
    if n and not bool(torch.isfinite(points).all()):
        raise ValueError("points contain NaN or Inf; drop or repair those Gaussians before voxelizing")
    batch_index = batch_index.long()
    num_scenes = int(batch_index.max()) + 1 if n else 0
    if n and int(batch_index.min()) < 0:
        raise ValueError("batch_index must be non-negative")
    pts = points.detach().double()  # float64: voxel assignment must not depend on rounding
    big = torch.finfo(torch.float64).max
    lo = torch.full((num_scenes, 3), big, dtype=torch.float64, device=points.device)
    hi = torch.full((num_scenes, 3), -big, dtype=torch.float64, device=points.device)
    idx3 = batch_index[:, None].expand(-1, 3)
    lo = lo.scatter_reduce(0, idx3, pts, reduce="amin")
    hi = hi.scatter_reduce(0, idx3, pts, reduce="amax")
    if lattice is not None and not (isinstance(lattice, int) and lattice >= 1):
        raise ValueError(f"lattice must be a positive number of voxels or None, got {lattice!r}")
    extent = (hi - lo).clamp_min(0).amax(dim=1)  # [B]
    if lattice is not None:  # the origin may move down by up to one lattice step: the cap allows for it
        extent = extent + lattice * voxel_size
    sizes = torch.maximum(torch.full_like(extent, voxel_size), extent / max(max_grid_extent - 1, 1))
    if lattice is not None and num_scenes:
        step = sizes[:, None] * lattice
        lo = torch.floor(lo / step) * step
    scaled = (pts - lo[batch_index]) / sizes[batch_index, None]
    coords = torch.floor(scaled).long()
    coords = coords.clamp_(0, max_grid_extent - 1)  # the scene maximum lands exactly on the cap
    offsets = (scaled - coords).clamp_(0.0, 1.0).float()
    sites, inverse = VoxelSites.from_coords(batch_index, coords)
    m = len(sites)
    if weights is None:
        pooled = features.new_zeros(m, features.shape[1]).index_add_(0, inverse, features)
        counts = torch.bincount(inverse, minlength=m).clamp_min(1).to(features.dtype)
        pooled = pooled / counts[:, None]
    else:
        if weights.shape != (n,) or (n and not bool((weights > 0).all())):
            raise ValueError(f"weights must be [{n}] and positive, got {tuple(weights.shape)}")
        w = weights.detach().to(features.dtype)
        pooled = features.new_zeros(m, features.shape[1]).index_add_(0, inverse, features * w[:, None])
        totals = features.new_zeros(m).index_add_(0, inverse, w)
        pooled = pooled / totals[:, None]
    return Voxelization(SparseVoxels(pooled, sites), inverse, sizes.float(), lo.float(), offsets)


def voxel_geometry_features(
    point_offsets: Tensor,  # [N, 3] positions inside the voxels, in [0, 1] (Voxelization.point_offsets)
    point_to_voxel: Tensor,  # [N] int64 voxel row of each point
    num_voxels: int,
    weights: "Tensor | None" = None,  # [N] positive, as the pooling's; None: every point counts once
) -> Tensor:  # [M, 9] float32
    """How the points lie inside each voxel: ``[2 m, 12 C]`` with ``m`` the weighted mean of ``u = offset - 0.5``
    (``[3]``, so ``2 m`` in [-1, 1]) and ``C = E[u u^T] - m m^T`` its weighted covariance as ``xx, yy, zz, xy, xz,
    yz`` (points spread uniformly along an axis give ``12 C = 1`` there; a plane through the voxel gives 0 along its
    normal). A voxel with one point has covariance 0. No gradient flows (positions are not network outputs)."""
    u = point_offsets.detach().float() - 0.5
    w = (torch.ones(u.shape[0], dtype=u.dtype, device=u.device) if weights is None
         else weights.detach().to(u.dtype))
    i, j = (0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2)
    totals = u.new_zeros(num_voxels).index_add_(0, point_to_voxel, w).clamp_min(1e-30)
    mean = u.new_zeros(num_voxels, 3).index_add_(0, point_to_voxel, u * w[:, None]) / totals[:, None]
    d = u - mean[point_to_voxel]  # centred first, so a voxel of one point has covariance exactly 0
    covariance = u.new_zeros(num_voxels, 6).index_add_(0, point_to_voxel, d[:, i] * d[:, j] * w[:, None])
    return torch.cat([2.0 * mean, 12.0 * covariance / totals[:, None]], dim=1)
