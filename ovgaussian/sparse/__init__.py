"""Sparse voxel convolution in pure torch: voxel keys, kernel maps, conv (custom autograd), batch norm."""

from ovgaussian.sparse.conv import DownConv3d, SubmanifoldConv3d, UpConv3d, sparse_conv
from ovgaussian.sparse.kernel_map import KernelMap, build_downsample_map, build_submanifold_map
from ovgaussian.sparse.norm import SparseBatchNorm
from ovgaussian.sparse.voxelize import (
    SparseVoxels, VoxelSites, Voxelization, pack_keys, voxel_geometry_features, voxelize_points,
)

__all__ = [
    "DownConv3d", "KernelMap", "SparseBatchNorm", "SparseVoxels", "SubmanifoldConv3d", "UpConv3d",
    "VoxelSites", "Voxelization", "build_downsample_map", "build_submanifold_map", "pack_keys",
    "sparse_conv", "voxel_geometry_features", "voxelize_points",
]
