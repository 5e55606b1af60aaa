"""A sum of per-row-chunk terms whose gradients are taken chunk by chunk during the forward pass.

A loss that is a sum of independent row terms (the 3D text cross-entropy over a million Gaussians) is too large
to keep its activations for backward, so it used to run in row chunks under activation checkpointing: each chunk's
forward ran twice (once for the value, once again in backward to rebuild its graph) before its backward.
:func:`eager_row_sum` instead builds each chunk's graph once, in the forward, and takes that chunk's gradients
with respect to the row tensors and the parameters right away; it keeps only those gradients (the size of the
inputs) and frees the chunk's activations. The backward of the sum is then the stored gradients times the incoming
scalar gradient (exact: the sum is linear in its terms). One forward and one backward per chunk instead of two
forwards and one backward, the same peak as checkpointing plus one gradient the size of the row inputs.

``fn`` must treat rows independently (no statistic over the rows) and return a scalar. Second derivatives are not
supported (the stored gradients are constants). Gradients are taken only for the inputs that need them; without
recorded gradients (``torch.no_grad``, evaluation), or for few rows, it is ``fn`` on the whole rows.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import Tensor

from ovgaussian.model import network as model


def eager_row_sum(
    fn: Callable[..., Tensor],  # (*row_chunks, *params) -> scalar
    rows: tuple[Tensor, ...],  # tensors sharing their first dimension, chunked together
    params: tuple[Tensor, ...],  # tensors passed whole to every chunk
    chunk_rows: int | None = None,
    min_rows: int | None = None,
) -> Tensor:  # scalar
    """``sum over row chunks of fn(*chunk, *params)``, differentiable in ``rows`` and ``params`` (module docstring).
    Chunks of ``chunk_rows`` (default ``model.CHECKPOINT_ROWS``) when gradients are recorded and there are more than
    ``max(chunk_rows, min_rows)`` rows (default ``model.CHECKPOINT_MIN_ROWS``), as ``model.checkpointed_rows``."""
    num = rows[0].shape[0]
    chunk_rows = model.CHECKPOINT_ROWS if chunk_rows is None else int(chunk_rows)
    min_rows = model.CHECKPOINT_MIN_ROWS if min_rows is None else int(min_rows)
    if chunk_rows < 1:
        raise ValueError(f"eager_row_sum: chunk_rows must be >= 1, got {chunk_rows}")
    if any(t.shape[0] != num for t in rows):
        raise ValueError(f"eager_row_sum: row tensors differ in rows: {[t.shape[0] for t in rows]}")
    if num <= max(chunk_rows, min_rows) or not torch.is_grad_enabled():
        return fn(*rows, *params)
    return _EagerRowSum.apply(fn, chunk_rows, len(rows), *rows, *params)


def gradients(value: Tensor, tensors: Sequence[Tensor], grad_output: Tensor | None = None) -> list[Tensor | None]:
    """``d value / d t`` for each of ``tensors`` (``grad_output`` the incoming gradient of a non-scalar ``value``):
    None where ``t`` needs no gradient or ``value`` does not depend on it; no autograd call when nothing needs one."""
    wrt = [t for t in tensors if t.requires_grad]
    if not (wrt and value.requires_grad):
        return [None] * len(tensors)
    found = iter(torch.autograd.grad(value, wrt, grad_output, allow_unused=True))
    return [next(found) if t.requires_grad else None for t in tensors]


def accumulate(total: Tensor | None, value: Tensor | None, scale: Tensor | None = None) -> Tensor | None:
    """``total + scale * value`` in place in ``total`` (a new tensor when ``total`` is None; ``value`` None: no
    change). ``value`` itself is never modified."""
    if value is None:
        return total
    value = value * scale if scale is not None else (value.clone() if total is None else value)
    return value if total is None else total.add_(value)


class _EagerRowSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, fn, chunk_rows, num_rows_tensors, *inputs):  # noqa: D102
        needs = ctx.needs_input_grad[3:]
        rows, params = inputs[:num_rows_tensors], inputs[num_rows_tensors:]
        wants_rows = [n and t.is_floating_point() for t, n in zip(rows, needs)]
        leaves = [p.detach().requires_grad_(n) for p, n in zip(params, needs[num_rows_tensors:])]
        param_grads: list[Tensor | None] = [None] * len(params)
        row_grads: list[list[Tensor]] = [[] for _ in rows]
        total = None
        with torch.enable_grad():
            for start in range(0, rows[0].shape[0], chunk_rows):
                parts = [t[start:start + chunk_rows].detach().requires_grad_(w) for t, w in zip(rows, wants_rows)]
                value = fn(*parts, *leaves)
                grads = gradients(value, (*parts, *leaves))
                for i, (part, g) in enumerate(zip(parts, grads)):
                    if part.requires_grad:
                        row_grads[i].append(torch.zeros_like(part) if g is None else g)
                for i, g in enumerate(grads[len(parts):]):
                    param_grads[i] = accumulate(param_grads[i], g)
                value = value.detach()
                total = value if total is None else total + value
        ctx.grads = [torch.cat(g) if w else None for g, w in zip(row_grads, wants_rows)] + [
            (torch.zeros_like(p) if g is None else g) if n else None
            for p, g, n in zip(params, param_grads, needs[num_rows_tensors:])]
        return total

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_total):  # noqa: D102
        grads, ctx.grads = ctx.grads, None
        return (None, None, None, *(None if g is None else g.mul_(grad_total) for g in grads))
