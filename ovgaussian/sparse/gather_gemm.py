"""Implicit-GEMM sparse convolution: gather each output row's neighbours side by side, one GEMM, no scatter.

A kernel map's plan (``gather_plan``: output rows grouped by neighbour pattern, the rest as a per-offset
residual, the identity offset apart) is applied here: each group's neighbours are gathered side by side
(im2col, zeros where absent) and multiplied by its offsets' stacked weights, one GEMM of inner dimension
``P * C_in`` per row block instead of one small GEMM plus a scatter-add per offset. All of it runs in a
fixed order (serial loops, no atomics): the results are deterministic.

Backward:
- input gradient: the same operation on the transposed map's plan with each ``weight[k]`` transposed (for a
  submanifold map, its own plan with the offsets reversed: the groups stay gather-only).
- weight gradient: per group ``im2col^T @ grad_out[rows]`` (the im2col block is gathered again in
  backward rather than kept, which would cost ``P * C_in`` floats per row per layer). When both gradients
  are needed (:func:`plan_backward`), the weight gradient instead reuses the input gradient's im2col of
  ``grad_out`` on the transposed plan, ``cols^T @ features[rows]``, so ``features``' im2col is not
  gathered a second time.

Work is done in row blocks of about :data:`GATHER_BLOCK_ELEMENTS` gathered values so the im2col
block stays in cache. Convolutions with fewer than :data:`MIN_GROUPED_CHANNELS` input channels use the
residual-only plan (the per-offset method plus the dense identity GEMM).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, NamedTuple

import torch
from torch import Tensor

import ovgaussian.sparse._numba_kernels as nk
from ovgaussian.sparse.gather_plan import GatherPlan, gather_plans, resolve_backend

if TYPE_CHECKING:
    from ovgaussian.sparse.kernel_map import KernelMap

#: Convolutions with fewer input channels than this use the residual-only plan (the per-offset
#: method): with narrow rows the im2col gather and the small GEMMs do not pay for the grouping.
MIN_GROUPED_CHANNELS = 16
#: Gathered values per im2col block (4 MB of float32). Each block's GEMM is one parallel region of
#: torch's 2 OpenMP threads; with 1 << 18 (about 270 rows at 8 x 96 columns) the threads' spin-waits
#: between the many small GEMMs cost more than the work on a loaded machine. Measured on a 1,000,000-
#: Gaussian room's finest level (56,725 voxels, 96 -> 96, forward + both gradients): 2 threads at load 6,
#: 2.97 s CPU with 1 << 18, 0.98 s with 1 << 20; with OMP_WAIT_POLICY=PASSIVE or 1 thread both sizes
#: take 0.36-0.44 s CPU (``benchmarks/results/paper_scale.md``).
GATHER_BLOCK_ELEMENTS = 1 << 20


class _BlockOps(NamedTuple):
    """im2col gather ``[n, P * C]``, row gather ``x[rows]``, ``out[rows] += y`` in row order (one backend)."""

    gather_neighbours: Callable[[Tensor, Tensor, Tensor], Tensor]  # (x, neighbours [n, P], out [n, P*C])
    gather_rows: Callable[[Tensor, Tensor, Tensor], Tensor]  # (x, rows [n], out [n, C])
    add_rows: Callable[[Tensor, Tensor, Tensor], None]  # (out, rows [n], y [n, C])


def _numba_block_ops() -> _BlockOps:
    def gather_neighbours(x: Tensor, neighbours: Tensor, out: Tensor) -> Tensor:
        nk.gather_neighbour_block(x.detach().numpy(), neighbours.numpy(), out.numpy())
        return out

    def gather_rows(x: Tensor, rows: Tensor, out: Tensor) -> Tensor:
        nk.gather_rows(x.detach().numpy(), rows.numpy(), out.numpy())
        return out

    def add_rows(out: Tensor, rows: Tensor, y: Tensor) -> None:
        nk.scatter_add_rows(out.numpy(), rows.numpy(), y.detach().numpy())

    return _BlockOps(gather_neighbours, gather_rows, add_rows)


def _torch_block_ops() -> _BlockOps:
    def gather_neighbours(x: Tensor, neighbours: Tensor, out: Tensor) -> Tensor:
        flat = neighbours.reshape(-1)
        absent = flat >= x.shape[0]
        rows = out.view(-1, x.shape[1])
        torch.index_select(x, 0, flat.clamp(max=max(x.shape[0] - 1, 0)), out=rows)
        rows.masked_fill_(absent[:, None], 0.0)
        return out

    def gather_rows(x: Tensor, rows: Tensor, out: Tensor) -> Tensor:
        return torch.index_select(x, 0, rows, out=out)

    def add_rows(out: Tensor, rows: Tensor, y: Tensor) -> None:
        out.index_add_(0, rows, y)

    return _BlockOps(gather_neighbours, gather_rows, add_rows)

def block_ops(backend: str, x: Tensor) -> _BlockOps:
    """Loops of the given backend (``"numba"``, ``"torch"`` or ``"auto"``, see :func:`gather_plan.resolve_backend`)."""
    backend = resolve_backend(backend, x)
    if backend == "numba":
        return _numba_block_ops()
    return _torch_block_ops()


def _block_rows(width: int) -> int:
    return max(1, GATHER_BLOCK_ELEMENTS // max(width, 1))


def apply_plan(features: Tensor, weight: Tensor, plan: GatherPlan, ops: _BlockOps) -> Tensor:
    """``[num_out, C_out]``: ``out[i] = sum_k features[nbr[i, k]] @ weight[k]`` (``weight [K, C_in, C_out]``).

    ``features [num_in, C_in]`` contiguous, no autograd (called inside the autograd Function).
    """
    return _apply_plan(features, weight, plan, ops, None)[0]


def _apply_plan(
    features: Tensor, weight: Tensor, plan: GatherPlan, ops: _BlockOps, out_rows_of: Tensor | None
) -> tuple[Tensor, Tensor | None]:
    """:func:`apply_plan`, and with ``out_rows_of [num_out, C]`` also ``sums [K, C_in, C]``: per offset ``k``, the sum
    over its pairs ``(in j, out i)`` of ``features[j]^T out_rows_of[i]``, from the same gathered blocks."""
    c_in, c_out = weight.shape[1], weight.shape[2]
    c_sum = 0 if out_rows_of is None else out_rows_of.shape[1]
    sums = None if out_rows_of is None else features.new_zeros(plan.kernel_volume, c_in, c_sum)
    if plan.identity_offset >= 0:
        out = features @ weight[plan.identity_offset]
        if sums is not None:
            torch.mm(features.t(), out_rows_of, out=sums[plan.identity_offset])
    else:
        out = features.new_zeros(plan.num_out, c_out)
    for group in plan.groups:
        p = group.offsets.numel()
        if p == 0:
            continue  # rows without any input stay zero
        stacked = weight.index_select(0, group.offsets).reshape(p * c_in, c_out)
        step = _block_rows(p * c_in)
        n = group.rows.numel()
        cols_buf = features.new_empty(min(step, n), p * c_in)
        prod_buf = features.new_empty(min(step, n), c_out)
        if sums is not None:
            acc = features.new_zeros(p * c_in, c_sum)  # block q: sums[offsets[q]]
            rows_buf = out_rows_of.new_empty(min(step, n), c_sum)
        for s in range(0, n, step):
            e = min(s + step, n)
            cols = ops.gather_neighbours(features, group.neighbours[s:e], cols_buf[: e - s])
            ops.add_rows(out, group.rows[s:e], torch.mm(cols, stacked, out=prod_buf[: e - s]))
            if sums is not None:
                acc.addmm_(cols.t(), ops.gather_rows(out_rows_of, group.rows[s:e], rows_buf[: e - s]))
        if sums is not None:
            sums.index_add_(0, group.offsets, acc.view(p, c_in, c_sum))
    residual = _residual_pairs(plan)
    if residual is not None:
        in_rows, out_rows, spans = residual
        x = ops.gather_rows(features, in_rows, features.new_empty(in_rows.numel(), c_in))
        y = features.new_empty(in_rows.numel(), c_out)
        for k, s, e in spans:
            torch.mm(x[s:e], weight[k], out=y[s:e])
        ops.add_rows(out, out_rows, y)  # offset by offset, each in row order: the adds of a per-offset loop
        if sums is not None:
            rows = ops.gather_rows(out_rows_of, out_rows, out_rows_of.new_empty(out_rows.numel(), c_sum))
            for k, s, e in spans:
                sums[k].addmm_(x[s:e].t(), rows[s:e])
    return out, sums


def _residual_pairs(plan: GatherPlan) -> tuple[Tensor, Tensor, list[tuple[int, int, int]]] | None:
    """The residual's pairs of every offset in one ``[R]`` input-row and one output-row tensor (offset by offset,
    each in its own order) and ``(k, start, end)`` of each non-empty offset's span; None without pairs. One gather,
    one scatter-add and the offsets' GEMMs on slices replace a gather, a GEMM and a scatter-add per offset."""
    spans, start = [], 0
    for k, rows in enumerate(plan.residual_in):
        if rows.numel():
            spans.append((k, start, start + rows.numel()))
            start += rows.numel()
    if not spans:
        return None
    return torch.cat(plan.residual_in), torch.cat(plan.residual_out), spans


def plan_weight_grad(features: Tensor, grad_out: Tensor, plan: GatherPlan, ops: _BlockOps) -> Tensor:
    """``[K, C_in, C_out]``: ``grad_w[k] = sum_i features[nbr[i, k]]^T grad_out[i]``."""
    c_in, c_out = features.shape[1], grad_out.shape[1]
    grad_weight = features.new_zeros(plan.kernel_volume, c_in, c_out)
    if plan.identity_offset >= 0:
        torch.mm(features.t(), grad_out, out=grad_weight[plan.identity_offset])
    for group in plan.groups:
        p = group.offsets.numel()
        if p == 0:
            continue
        step = _block_rows(p * c_in)
        n = group.rows.numel()
        acc = features.new_zeros(p * c_in, c_out)
        cols_buf = features.new_empty(min(step, n), p * c_in)
        g_buf = features.new_empty(min(step, n), c_out)
        for s in range(0, n, step):
            e = min(s + step, n)
            cols = ops.gather_neighbours(features, group.neighbours[s:e], cols_buf[: e - s])
            acc.addmm_(cols.t(), ops.gather_rows(grad_out, group.rows[s:e], g_buf[: e - s]))
        grad_weight.index_add_(0, group.offsets, acc.view(p, c_in, c_out))
    residual = _residual_pairs(plan)
    if residual is not None:
        in_rows, out_rows, spans = residual
        x = ops.gather_rows(features, in_rows, features.new_empty(in_rows.numel(), c_in))
        g = ops.gather_rows(grad_out, out_rows, grad_out.new_empty(out_rows.numel(), c_out))
        for k, s, e in spans:
            grad_weight[k].addmm_(x[s:e].t(), g[s:e])
    return grad_weight


def plan_backward(
    features: Tensor, grad_out: Tensor, weight: Tensor, plan_t: GatherPlan, ops: _BlockOps
) -> tuple[Tensor, Tensor]:
    """``(grad_features [num_in, C_in], grad_weight [K, C_in, C_out])`` in one pass over the transposed plan.

    Equal to ``apply_plan(grad_out, weight^T, plan_t)`` and ``plan_weight_grad(features, grad_out, plan)``, but
    each im2col block of ``grad_out`` is gathered once and feeds both products. A pair of the transposed map,
    ``(in b, out a, weight k)``, is the forward's ``(in a, out b, k)``, so ``grad_w[k] += features[a]^T
    grad_out[b]``: per group ``cols^T @ features[rows]`` gives the ``[P * C_out, C_in]`` transposed blocks of
    its offsets' weight gradients. The weight gradient then gathers ``features[rows]`` (rows increasing: about
    sequential) instead of the forward's im2col of ``features`` again.
    """
    grad_features, grad_weight_t = _apply_plan(grad_out, weight.transpose(1, 2), plan_t, ops, features)
    return grad_features, grad_weight_t.transpose(1, 2).contiguous()


class _GatherGemmFunction(torch.autograd.Function):
    @staticmethod
    def forward(  # noqa: D102
        ctx, features: Tensor, weight: Tensor, plan: GatherPlan, plan_t: GatherPlan, ops: _BlockOps
    ) -> Tensor:
        ctx.save_for_backward(features, weight)
        ctx.plan, ctx.plan_t, ctx.ops = plan, plan_t, ops
        return apply_plan(features, weight.contiguous(), plan, ops)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # noqa: D102
        features, weight = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        grad_features = grad_weight = None
        if ctx.needs_input_grad[0] and ctx.needs_input_grad[1]:
            grad_features, grad_weight = plan_backward(features, grad_out, weight, ctx.plan_t, ctx.ops)
            return grad_features, grad_weight, None, None, None
        if ctx.needs_input_grad[0]:
            grad_features = apply_plan(grad_out, weight.transpose(1, 2), ctx.plan_t, ctx.ops)
        if ctx.needs_input_grad[1]:
            grad_weight = plan_weight_grad(features, grad_out, ctx.plan, ctx.ops)
        return grad_features, grad_weight, None, None, None


def gather_gemm_conv(
    features: Tensor, weight: Tensor, kernel_map: "KernelMap", backend: str = "auto",
    plans: tuple[GatherPlan, GatherPlan] | None = None,
) -> Tensor:
    """``[num_out, C_out]`` implicit-GEMM sparse convolution (shapes checked by ``sparse_conv``).

    ``plans``: ``(plan, transposed plan)`` to use instead of the map's cached :func:`gather_plans`.
    """
    if plans is None:
        plans = gather_plans(kernel_map, grouped=weight.shape[1] >= MIN_GROUPED_CHANNELS)
    plan, plan_t = plans
    features = features.contiguous()
    return _GatherGemmFunction.apply(features, weight, plan, plan_t, block_ops(backend, features))
