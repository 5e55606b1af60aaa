"""Batch normalization over the active voxels of a batch of scenes (the rows of ``features``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ovgaussian.sparse.voxelize import SparseVoxels

#: Added to the variance before the square root (as ``nn.BatchNorm1d``); keeps a constant channel
#: (including the single-voxel batch, whose variance is exactly 0) finite.
BATCH_NORM_EPS = 1e-5
#: Weight of the current batch in the running statistics (as ``nn.BatchNorm1d``).
BATCH_NORM_MOMENTUM = 0.1


def batch_norm_rows(
    features: Tensor,  # [M, C]
    weight: Tensor,  # [C]
    bias: Tensor,  # [C]
    running_mean: Tensor,  # [C], updated in place in training
    running_var: Tensor,  # [C], updated in place in training
    training: bool,
    momentum: float = BATCH_NORM_MOMENTUM,
    eps: float = BATCH_NORM_EPS,
) -> Tensor:
    """``nn.BatchNorm1d`` semantics, also defined for 0 and 1 rows in training.

    With 0 rows the output is empty and the statistics are unchanged. With 1 row the batch variance
    is 0 (the output is ``bias``); the running mean is updated and the running variance is not
    (its unbiased estimate is undefined).
    """
    m = features.shape[0]
    if m == 0:
        return features.new_zeros(0, weight.shape[0]) + 0 * (weight + bias)  # keeps the graph connected
    if not training or m > 1:
        return F.batch_norm(features, running_mean, running_var, weight, bias, training, momentum, eps)
    mean = features.mean(dim=0)
    with torch.no_grad():
        running_mean.mul_(1 - momentum).add_(momentum * mean)
    centred = features - mean
    return centred * torch.rsqrt(centred.square().mean(dim=0) + eps) * weight + bias


class SparseBatchNorm(nn.Module):
    """Batch norm of the voxel features of a :class:`SparseVoxels` (statistics over all active sites)."""

    def __init__(self, num_channels: int, momentum: float = BATCH_NORM_MOMENTUM, eps: float = BATCH_NORM_EPS) -> None:
        super().__init__()
        self.num_channels, self.momentum, self.eps = num_channels, momentum, eps
        self.weight = nn.Parameter(torch.ones(num_channels))
        self.bias = nn.Parameter(torch.zeros(num_channels))
        self.register_buffer("running_mean", torch.zeros(num_channels))
        self.register_buffer("running_var", torch.ones(num_channels))

    def forward(self, x: SparseVoxels) -> SparseVoxels:
        out = batch_norm_rows(
            x.features, self.weight, self.bias, self.running_mean, self.running_var, self.training,
            self.momentum, self.eps,
        )
        return SparseVoxels(out, x.sites)

    def extra_repr(self) -> str:
        return f"{self.num_channels}, momentum={self.momentum}, eps={self.eps}"
