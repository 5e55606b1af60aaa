"""Sparse 3D convolution with a hand-written backward, two methods.

``sparse_conv(features, weight, kernel_map)`` computes, for every kernel offset ``k``,
``out[out_k] += features[in_k] @ weight[k]``.

- ``method="gemm"`` (default): implicit GEMM (``gather_gemm.py``): output rows grouped by neighbour
  pattern, each group's neighbours gathered side by side and one GEMM per row block; the pairs of
  rare patterns (and every pair of convs with under 16 input channels) go per offset.
- ``method="scatter"`` (the previous implementation, kept as a second reference and fallback): per
  offset gather, matmul, scatter-add; backward ``grad_features[in_k] += grad_out[out_k] @ weight[k]^T``
  and ``grad_weight[k] = features[in_k]^T @ grad_out[out_k]``.

Both custom autograd Functions keep only the input features and weight for backward (plain autograd
would keep every gathered block).

Weight layout: ``[K, C_in, C_out]`` with ``K`` the kernel offsets in ``(dx, dy, dz)`` lexicographic
order. ``reference.py`` gives the equivalent dense ``conv3d`` / ``conv_transpose3d`` weights.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import torch
from torch import Tensor, nn

from ovgaussian.sparse._numba_kernels import gather_rows, scatter_add_rows
from ovgaussian.sparse.gather_gemm import gather_gemm_conv
from ovgaussian.sparse.kernel_map import KernelMap
from ovgaussian.sparse.voxelize import SparseVoxels


class RowOps(NamedTuple):
    """Row gather ``x[rows]`` and in-place row scatter-add ``out[rows] += y`` (one backend)."""

    gather: Callable[[Tensor, Tensor], Tensor]
    scatter_add: Callable[[Tensor, Tensor, Tensor], None]


def torch_row_ops() -> RowOps:
    """``index_select`` / ``index_add_`` (the reference backend, and the fallback without numba)."""
    return RowOps(lambda x, rows: x.index_select(0, rows), lambda out, rows, y: out.index_add_(0, rows, y))


def numba_row_ops() -> RowOps:
    """Serial numba loops on the tensors' memory (same results as :func:`torch_row_ops`, 2-3x faster)."""
    def gather(x: Tensor, rows: Tensor) -> Tensor:
        out = x.new_empty(rows.shape[0], x.shape[1])
        gather_rows(x.detach().contiguous().numpy(), rows.contiguous().numpy(), out.numpy())
        return out

    def scatter_add(out: Tensor, rows: Tensor, y: Tensor) -> None:
        scatter_add_rows(out.detach().numpy(), rows.contiguous().numpy(), y.detach().contiguous().numpy())

    return RowOps(gather, scatter_add)


def default_row_ops() -> RowOps:
    """Numba row ops (CPU tensors; other devices use :func:`torch_row_ops`)."""
    return numba_row_ops()


class _SparseConvFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, weight: Tensor, kernel_map: KernelMap, ops: RowOps) -> Tensor:  # noqa: D102
        out = features.new_zeros(kernel_map.num_out, weight.shape[2])
        for k in range(kernel_map.kernel_volume):
            in_rows = kernel_map.in_indices[k]
            if in_rows.numel() == 0:
                continue
            if kernel_map.identity[k]:
                out.addmm_(features, weight[k])
            else:
                ops.scatter_add(out, kernel_map.out_indices[k], ops.gather(features, in_rows) @ weight[k])
        ctx.save_for_backward(features, weight)
        ctx.kernel_map, ctx.ops = kernel_map, ops
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # noqa: D102
        features, weight = ctx.saved_tensors
        kernel_map: KernelMap = ctx.kernel_map
        ops: RowOps = ctx.ops
        need_features, need_weight = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_out = grad_out.contiguous()
        grad_features = torch.zeros_like(features) if need_features else None
        grad_weight = torch.zeros_like(weight) if need_weight else None
        for k in range(kernel_map.kernel_volume):
            in_rows = kernel_map.in_indices[k]
            if in_rows.numel() == 0:
                continue
            if kernel_map.identity[k]:
                g, x = grad_out, features
            else:
                g = ops.gather(grad_out, kernel_map.out_indices[k])
                x = ops.gather(features, in_rows) if need_weight else None
            if need_weight:
                torch.mm(x.t(), g, out=grad_weight[k])
            if need_features:
                if kernel_map.identity[k]:
                    grad_features.addmm_(g, weight[k].t())
                else:
                    ops.scatter_add(grad_features, in_rows, g @ weight[k].t())
        return grad_features, grad_weight, None, None


def sparse_conv(
    features: Tensor, weight: Tensor, kernel_map: KernelMap, method: str = "gemm", backend: str = "auto"
) -> Tensor:
    """``[num_out, C_out]`` sparse convolution of ``features [num_in, C_in]`` by ``weight [K, C_in, C_out]``.

    Args:
        method: ``"gemm"`` (implicit GEMM, default) or ``"scatter"`` (per-offset gather/matmul/scatter).
        backend: row gather/scatter loops: ``"numba"``, ``"torch"`` or ``"auto"`` (numba on CPU when it
            imports).
    """
    if weight.ndim != 3 or weight.shape[0] != kernel_map.kernel_volume:
        raise ValueError(f"weight {tuple(weight.shape)} does not match a {kernel_map.kernel_volume}-offset map")
    if features.ndim != 2 or features.shape[0] != kernel_map.num_in or features.shape[1] != weight.shape[1]:
        raise ValueError(
            f"features {tuple(features.shape)} do not match {kernel_map.num_in} input sites x {weight.shape[1]} channels"
        )
    if features.dtype != weight.dtype:
        raise ValueError(f"features are {features.dtype}, weight is {weight.dtype}")
    if method == "gemm":
        return gather_gemm_conv(features, weight, kernel_map, backend)
    if method != "scatter":
        raise ValueError(f"method must be 'gemm' or 'scatter', got {method!r}")
    return scatter_conv(features, weight, kernel_map, _row_ops(backend, features))


def _row_ops(backend: str, features: Tensor) -> RowOps:
    if backend == "auto":
        return default_row_ops() if features.device.type == "cpu" else torch_row_ops()
    if backend == "numba":
        return numba_row_ops()
    if backend == "torch":
        return torch_row_ops()
    raise ValueError(f"backend must be 'auto', 'numba' or 'torch', got {backend!r}")


def scatter_conv(features: Tensor, weight: Tensor, kernel_map: KernelMap, ops: RowOps | None = None) -> Tensor:
    """The per-offset gather/matmul/scatter-add method (no shape checks: call :func:`sparse_conv`)."""
    if ops is None:
        ops = _row_ops("auto", features)
    return _SparseConvFunction.apply(features.contiguous(), weight, kernel_map, ops)


def sparse_conv_autograd(features: Tensor, weight: Tensor, kernel_map: KernelMap) -> Tensor:
    """Same as :func:`sparse_conv` with plain autograd (the comparison baseline in the benchmark)."""
    out = features.new_zeros(kernel_map.num_out, weight.shape[2])
    for k in range(kernel_map.kernel_volume):
        if kernel_map.in_indices[k].numel():
            out = out.index_add(0, kernel_map.out_indices[k], features[kernel_map.in_indices[k]] @ weight[k])
    return out


def _init_weight(weight: Tensor, fan_in: int) -> None:
    """Kaiming-uniform for a ReLU network over ``fan_in`` inputs (as ``nn.Conv3d`` does)."""
    bound = 1.0 / math.sqrt(max(fan_in, 1)) * math.sqrt(3.0)
    with torch.no_grad():
        weight.uniform_(-bound, bound)


class _SparseConvBase(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, kernel_volume: int, bias: bool) -> None:
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.weight = nn.Parameter(torch.empty(kernel_volume, in_channels, out_channels))
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None
        _init_weight(self.weight, kernel_volume * in_channels)

    def _apply_map(self, x: SparseVoxels, kernel_map: KernelMap, sites) -> SparseVoxels:
        out = sparse_conv(x.features, self.weight, kernel_map)
        if self.bias is not None:
            out = out + self.bias
        return SparseVoxels(out, sites)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel_volume={self.weight.shape[0]}"


class SubmanifoldConv3d(_SparseConvBase):
    """Odd cubic kernel, outputs on the input sites (dense ``conv3d`` with padding ``k // 2``, sampled there)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, kernel_size**3, bias)
        self.kernel_size = kernel_size

    def forward(self, x: SparseVoxels) -> SparseVoxels:
        if self.kernel_size == 1:
            out = x.features @ self.weight[0]
            return SparseVoxels(out + self.bias if self.bias is not None else out, x.sites)
        return self._apply_map(x, x.sites.submanifold_map(self.kernel_size), x.sites)


class DownConv3d(_SparseConvBase):
    """Kernel 2, stride 2: outputs on ``unique(floor(coords / 2))`` (dense ``conv3d(k=2, s=2)``)."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 8, bias)

    def forward(self, x: SparseVoxels) -> SparseVoxels:
        coarse, kernel_map = x.sites.downsample()
        return self._apply_map(x, kernel_map, coarse)


class UpConv3d(_SparseConvBase):
    """Transposed kernel 2, stride 2 back onto the cached finer sites (dense ``conv_transpose3d(k=2, s=2)``)."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 8, bias)

    def forward(self, x: SparseVoxels, fine_sites) -> SparseVoxels:
        coarse, kernel_map = fine_sites.downsample()
        if coarse is not x.sites and not torch.equal(coarse.keys, x.sites.keys):
            raise ValueError("UpConv3d: input sites are not the downsampling of fine_sites")
        return self._apply_map(x, kernel_map.transposed(), fine_sites)
