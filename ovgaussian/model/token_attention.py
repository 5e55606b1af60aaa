"""The adapter's attention: one query per row over that row's ``T`` attribute tokens, per head, forward and backward.

For a row with query ``q [H, d]`` and token keys and values ``k, v [T, H, d]`` (``T = 4`` or 5 tokens, ``H = 4``
heads of ``d = 4`` channels in the default network):

    w[t, h]  = softmax over t of  (q[h] . k[t, h]) * scale
    out[h]   = sum over t of  w[t, h] v[t, h]

Written as torch elementwise products and sums over ``[N, T, H, d]`` (:func:`token_attention_reference`), every
step is a pass over memory with a few flops per element: about a fifth of the adapter's time per 1,000,000
Gaussians. :func:`token_attention` does each row's forward, and its backward, in one numba loop over the rows
(CPU tensors; any other device takes the reference). Backward, with ``g = d out``:

    dw[t, h]  = g[h] . v[t, h]
    dl[t, h]  = w[t, h] (dw[t, h] - sum over t' of w[t', h] dw[t', h]) * scale       (softmax's backward)
    dq[h]     = sum over t of dl[t, h] k[t, h];   dk[t, h] = dl[t, h] q[h];   dv[t, h] = w[t, h] g[h]
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from seggaussian.render.parallel import GAUSSIANS_PER_CHUNK, run_parallel

#: ``reassoc`` lets the short sums run on SIMD lanes; no flag that assumes finite values or approximates a division.
_JIT = dict(cache=True, nogil=True, fastmath={"reassoc", "contract"})


def token_attention_reference(q: Tensor, k: Tensor, v: Tensor) -> Tensor:
    """``[N, H, d]`` attention of ``q [N, H, d]`` over ``k, v [N, T, H, d]`` (module docstring), scale ``1/sqrt(d)``:
    torch elementwise products and sums (autograd gives the backward)."""
    d = q.shape[2]
    weights = torch.softmax((k * q[:, None]).sum(-1) / math.sqrt(d), dim=1)  # [N, T, H]
    return (weights[..., None] * v).sum(1)


def token_attention(q: Tensor, k: Tensor, v: Tensor) -> Tensor:
    """:func:`token_attention_reference` with the numba forward and backward on CPU tensors."""
    if q.ndim != 3 or k.ndim != 4 or k.shape != v.shape or k.shape[0] != q.shape[0] or k.shape[2:] != q.shape[1:]:
        raise ValueError(f"token_attention: q must be [N, H, d] and k, v [N, T, H, d], got {tuple(q.shape)}, "
                         f"{tuple(k.shape)}, {tuple(v.shape)}")
    if q.device.type != "cpu" or q.dtype not in (torch.float32, torch.float64) or not (q.dtype == k.dtype == v.dtype):
        return token_attention_reference(q, k, v)
    return _TokenAttention.apply(q, k, v)


def token_attention_packed(q: Tensor, kv: Tensor) -> Tensor:
    """:func:`token_attention` of ``q [N, H, d]`` over keys ``kv[:, :, 0]`` and values ``kv[:, :, 1]`` of one
    ``[N, T, 2, H, d]`` tensor: keys and values come from one product (``ovgaussian.model.network``'s adapter), and
    the kernels read and write them in place, so neither a copy in the forward nor a zero-filled gradient per half
    in the backward is made."""
    if kv.ndim != 5 or kv.shape[2] != 2:
        raise ValueError(f"token_attention_packed: kv must be [N, T, 2, H, d], got {tuple(kv.shape)}")
    if q.ndim != 3 or kv.shape[0] != q.shape[0] or kv.shape[3:] != q.shape[1:]:
        raise ValueError(f"token_attention_packed: q must be [N, H, d] and kv [N, T, 2, H, d], got "
                         f"{tuple(q.shape)}, {tuple(kv.shape)}")
    if q.device.type != "cpu" or q.dtype not in (torch.float32, torch.float64) or q.dtype != kv.dtype:
        return token_attention(q, kv[:, :, 0], kv[:, :, 1])
    return _PackedTokenAttention.apply(q, kv)


def _attend(q: Tensor, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """``(out [N, H, d], weights [N, T, H])`` by the numba kernels; ``k``, ``v`` may be strided views."""
    n, t, h, d = k.shape
    out = q.new_empty(n, h, d)
    weights = q.new_empty(n, t, h)
    if n:
        kernel = _forward_rows_d4 if d == 4 else _forward_rows
        run_parallel(kernel, q.detach().numpy(), k.detach().numpy(), v.detach().numpy(), _scale(q),
                     out.numpy(), weights.numpy(), chunk=GAUSSIANS_PER_CHUNK)
    return out, weights


def _attend_backward(q, k, v, weights, grad_out, grad_q, grad_k, grad_v) -> None:
    """Fill ``grad_q``, ``grad_k``, ``grad_v`` (may be strided views) by the numba kernels."""
    if q.shape[0]:
        kernel = _backward_rows_d4 if q.shape[2] == 4 else _backward_rows
        run_parallel(kernel, q.detach().numpy(), k.detach().numpy(), v.detach().numpy(), weights.numpy(),
                     grad_out.numpy(), _scale(q), grad_q.numpy(), grad_k.numpy(), grad_v.numpy(),
                     chunk=GAUSSIANS_PER_CHUNK)


class _TokenAttention(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, k, v):  # noqa: D102
        q, k, v = q.contiguous(), k.contiguous(), v.contiguous()
        out, weights = _attend(q, k, v)
        ctx.save_for_backward(q, k, v, weights)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        q, k, v, weights = ctx.saved_tensors
        grad_q, grad_k, grad_v = torch.empty_like(q), torch.empty_like(k), torch.empty_like(v)
        _attend_backward(q, k, v, weights, grad_out.contiguous(), grad_q, grad_k, grad_v)
        return grad_q, grad_k, grad_v


class _PackedTokenAttention(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, kv):  # noqa: D102
        q, kv = q.contiguous(), kv.contiguous()
        out, weights = _attend(q, kv[:, :, 0], kv[:, :, 1])
        ctx.save_for_backward(q, kv, weights)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        q, kv, weights = ctx.saved_tensors
        grad_q, grad_kv = torch.empty_like(q), torch.empty_like(kv)
        _attend_backward(q, kv[:, :, 0], kv[:, :, 1], weights, grad_out.contiguous(), grad_q, grad_kv[:, :, 0],
                         grad_kv[:, :, 1])
        return grad_q, grad_kv


def _scale(q: Tensor) -> np.ndarray:
    """``[1/sqrt(d)]`` in ``q``'s dtype: the kernels then compute in that dtype throughout (a Python float would
    promote float32 rows to float64 and take the slower double ``exp``)."""
    return np.array([1.0 / math.sqrt(q.shape[2])], dtype=q.detach().numpy().dtype)


@numba.njit(parallel=True, **_JIT)
def _forward_rows(q, k, v, scale, out, weights):  # pragma: no cover - compiled
    """``out [N, H, d]`` and the softmax ``weights [N, T, H]`` (module docstring)."""
    n, t, h, d = k.shape
    sc = scale[0]
    for i in prange(n):
        for hh in range(h):
            top = q[i, hh, 0] * k[i, 0, hh, 0] * sc
            for tt in range(t):
                acc = q[i, hh, 0] * k[i, tt, hh, 0]
                for dd in range(1, d):
                    acc += q[i, hh, dd] * k[i, tt, hh, dd]
                logit = acc * sc
                weights[i, tt, hh] = logit
                if tt == 0 or logit > top:
                    top = logit
            total = sc - sc  # zero in the dtype
            for tt in range(t):
                e = np.exp(weights[i, tt, hh] - top)
                weights[i, tt, hh] = e
                total += e
            for tt in range(t):
                weights[i, tt, hh] /= total
            for dd in range(d):
                acc = weights[i, 0, hh] * v[i, 0, hh, dd]
                for tt in range(1, t):
                    acc += weights[i, tt, hh] * v[i, tt, hh, dd]
                out[i, hh, dd] = acc


@numba.njit(parallel=True, **_JIT)
def _backward_rows(q, k, v, weights, grad_out, scale, grad_q, grad_k, grad_v):  # pragma: no cover - compiled
    """Gradients of ``q``, ``k``, ``v`` from ``grad_out [N, H, d]`` (module docstring)."""
    n, t, h, d = k.shape
    sc = scale[0]
    for i in prange(n):
        for hh in range(h):
            mean = sc - sc  # sum over t of w dw (zero in the dtype)
            for tt in range(t):
                dw = grad_out[i, hh, 0] * v[i, tt, hh, 0]
                for dd in range(1, d):
                    dw += grad_out[i, hh, dd] * v[i, tt, hh, dd]
                mean += weights[i, tt, hh] * dw
            for dd in range(d):
                grad_q[i, hh, dd] = mean - mean
            for tt in range(t):
                w = weights[i, tt, hh]
                dw = grad_out[i, hh, 0] * v[i, tt, hh, 0]
                for dd in range(1, d):
                    dw += grad_out[i, hh, dd] * v[i, tt, hh, dd]
                dl = w * (dw - mean) * sc
                for dd in range(d):
                    grad_q[i, hh, dd] += dl * k[i, tt, hh, dd]
                    grad_k[i, tt, hh, dd] = dl * q[i, hh, dd]
                    grad_v[i, tt, hh, dd] = w * grad_out[i, hh, dd]


@numba.njit(parallel=True, **_JIT)
def _forward_rows_d4(q, k, v, scale, out, weights):  # pragma: no cover - compiled
    """:func:`_forward_rows` for ``d = 4`` (the default network): each head's query, sums and output in scalar
    registers, 1.8x faster per row (benchmarks/results/train.md)."""
    n, t, h = k.shape[0], k.shape[1], k.shape[2]
    sc = scale[0]
    for i in prange(n):
        for hh in range(h):
            q0, q1, q2, q3 = q[i, hh, 0] * sc, q[i, hh, 1] * sc, q[i, hh, 2] * sc, q[i, hh, 3] * sc
            top = q0 * k[i, 0, hh, 0] + q1 * k[i, 0, hh, 1] + q2 * k[i, 0, hh, 2] + q3 * k[i, 0, hh, 3]
            for tt in range(t):
                logit = q0 * k[i, tt, hh, 0] + q1 * k[i, tt, hh, 1] + q2 * k[i, tt, hh, 2] + q3 * k[i, tt, hh, 3]
                weights[i, tt, hh] = logit
                top = max(top, logit)
            total = sc - sc  # zero in the dtype
            for tt in range(t):
                e = np.exp(weights[i, tt, hh] - top)
                weights[i, tt, hh] = e
                total += e
            inv = 1 / total
            o0 = o1 = o2 = o3 = sc - sc
            for tt in range(t):
                w = weights[i, tt, hh] * inv
                weights[i, tt, hh] = w
                o0 += w * v[i, tt, hh, 0]
                o1 += w * v[i, tt, hh, 1]
                o2 += w * v[i, tt, hh, 2]
                o3 += w * v[i, tt, hh, 3]
            out[i, hh, 0], out[i, hh, 1], out[i, hh, 2], out[i, hh, 3] = o0, o1, o2, o3


@numba.njit(parallel=True, **_JIT)
def _backward_rows_d4(q, k, v, weights, grad_out, scale, grad_q, grad_k, grad_v):  # pragma: no cover - compiled
    """:func:`_backward_rows` for ``d = 4``, in scalar registers as :func:`_forward_rows_d4`."""
    n, t, h = k.shape[0], k.shape[1], k.shape[2]
    sc = scale[0]
    for i in prange(n):
        for hh in range(h):
            g0, g1, g2, g3 = grad_out[i, hh, 0], grad_out[i, hh, 1], grad_out[i, hh, 2], grad_out[i, hh, 3]
            mean = sc - sc  # sum over t of w dw
            for tt in range(t):
                dw = g0 * v[i, tt, hh, 0] + g1 * v[i, tt, hh, 1] + g2 * v[i, tt, hh, 2] + g3 * v[i, tt, hh, 3]
                mean += weights[i, tt, hh] * dw
            q0, q1, q2, q3 = q[i, hh, 0], q[i, hh, 1], q[i, hh, 2], q[i, hh, 3]
            d0 = d1 = d2 = d3 = sc - sc
            for tt in range(t):
                w = weights[i, tt, hh]
                dw = g0 * v[i, tt, hh, 0] + g1 * v[i, tt, hh, 1] + g2 * v[i, tt, hh, 2] + g3 * v[i, tt, hh, 3]
                dl = w * (dw - mean) * sc
                d0 += dl * k[i, tt, hh, 0]
                d1 += dl * k[i, tt, hh, 1]
                d2 += dl * k[i, tt, hh, 2]
                d3 += dl * k[i, tt, hh, 3]
                grad_k[i, tt, hh, 0], grad_k[i, tt, hh, 1] = dl * q0, dl * q1
                grad_k[i, tt, hh, 2], grad_k[i, tt, hh, 3] = dl * q2, dl * q3
                grad_v[i, tt, hh, 0], grad_v[i, tt, hh, 1] = w * g0, w * g1
                grad_v[i, tt, hh, 2], grad_v[i, tt, hh, 3] = w * g2, w * g3
            grad_q[i, hh, 0], grad_q[i, hh, 1], grad_q[i, hh, 2], grad_q[i, hh, 3] = d0, d1, d2, d3
