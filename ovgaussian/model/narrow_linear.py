"""A linear layer for inputs with few columns: its weight gradient is computed as ``(x^T g)^T``, not ``g^T x``.

``F.linear``'s backward forms the weight gradient ``[out, in]`` as ``grad^T @ x`` over the rows: a product whose
left operand is a transposed ``[rows, out]`` tensor. For the adapter's token embedding (11 attribute columns to 64
token channels, 32,768 rows) MKL took 2.7 ms for it, and 0.77 ms for the same numbers as ``(x^T @ grad)^T``
(2 threads). :func:`narrow_linear` is ``F.linear`` with that backward;
values and gradients equal ``F.linear``'s up to float summation order (tests).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def narrow_linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``F.linear(x, weight, bias)`` (``x [N, in]``, ``weight [out, in]``) with the weight gradient as
    ``(x^T grad)^T``."""
    if x.ndim != 2 or weight.ndim != 2 or x.shape[1] != weight.shape[1]:
        raise ValueError(f"narrow_linear: x must be [N, {weight.shape[-1]}] for weight {tuple(weight.shape)}, "
                         f"got {tuple(x.shape)}")
    return _NarrowLinear.apply(x, weight, bias)


class _NarrowLinear(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, bias):  # noqa: D102
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return F.linear(x, weight, bias)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # noqa: D102
        x, weight = ctx.saved_tensors
        need_x, need_w, need_b = ctx.needs_input_grad
        return (grad @ weight if need_x else None,
                (x.T @ grad).T if need_w else None,
                grad.sum(0) if need_b and ctx.has_bias else None)
