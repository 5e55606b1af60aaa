"""``Linear (ReLU Linear)*`` with its bias + ReLU and the ReLU's backward as one numba pass each (the adapter's MLP).

Autograd's graph of ``nn.Sequential(Linear, ReLU, Linear, ReLU, Linear)`` makes, per hidden layer and per chunk of
rows: a copy of the broadcast bias into the product's output (``addmm``), a new tensor for the ReLU, and in the
backward the ReLU's mask and the bias gradient's column sum, each a pass over ``[rows, 96]`` (12 MB per 32,768
rows). :func:`relu_mlp` keeps the products in torch and does each hidden layer's elementwise work in one loop over
the rows: ``h = max(x W^T + b, 0)`` in place of the product, and in the backward ``g = g * (h > 0)`` in place with the
column sums of ``g`` (the bias gradient) per block of rows, added in a fixed order (deterministic). The
``nn.Sequential`` itself is the reference; the tests compare values and every gradient, on degenerate rows too.
CPU float32 / float64 tensors; anything else (or another layer layout) runs the ``nn.Sequential``.
"""

from __future__ import annotations

import numba
import torch
import torch.nn.functional as F
from numba import prange
from torch import Tensor, nn

from seggaussian.render.parallel import SUM_BLOCK_ROWS, dtype_scalars, run_parallel, sum_blocks

#: ``reassoc`` lets the column sums run on SIMD lanes; no flag that assumes finite values.
_JIT = dict(cache=True, nogil=True, fastmath={"reassoc", "contract"})


def relu_mlp(mlp: nn.Module, x: Tensor, first: "tuple[Tensor, Tensor] | None" = None) -> Tensor:  # [N, in] -> [N, out]
    """``mlp(x)`` for ``mlp = nn.Sequential(Linear, ReLU, ..., Linear)`` (module docstring).

    ``first``: ``(weight [hidden, in], bias [hidden])`` used in place of the first layer's own (e.g. that layer with
    a preceding linear map folded in); gradients flow to whatever they were computed from."""
    layers = _linear_layers(mlp)
    if layers is None or x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64) or any(
            layer.weight.dtype != x.dtype for layer in layers):
        if first is None:
            return mlp(x)
        return mlp[1:](F.linear(x, *first))
    params = [t for layer in layers for t in (layer.weight, layer.bias)]
    if first is not None:
        params[:2] = first
    return _ReluMLP.apply(x, *params)


def _linear_layers(mlp: nn.Module) -> "list[nn.Linear] | None":
    """The Linear layers of ``Sequential(Linear, ReLU, Linear, ..., Linear)`` (every Linear with a bias), or None."""
    modules = list(mlp) if isinstance(mlp, nn.Sequential) else []
    if len(modules) % 2 == 0:
        return None
    for i, module in enumerate(modules):
        want = nn.Linear if i % 2 == 0 else nn.ReLU
        if type(module) is not want or (want is nn.Linear and module.bias is None):
            return None
    return modules[::2]


class _ReluMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, *params):  # noqa: D102
        weights, biases = params[0::2], params[1::2]
        hidden = [x]  # each layer's input: x, then the hidden layers' ReLU outputs
        h = x.contiguous()
        for w, b in zip(weights[:-1], biases[:-1]):
            h = h @ w.T
            if h.shape[0]:
                run_parallel(bias_relu_rows, h.numpy(), b.detach().contiguous().numpy(),
                             dtype_scalars(0, h.numpy().dtype), chunk=0)
            hidden.append(h)
        out = torch.addmm(biases[-1], h, weights[-1].T)
        ctx.save_for_backward(*hidden, *weights)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        saved = ctx.saved_tensors
        layers = len(saved) // 2
        hidden, weights = saved[:layers], saved[layers:]
        need = ctx.needs_input_grad  # x, then (weight, bias) per layer
        grads: list[Tensor | None] = []
        g = grad_out.contiguous()  # the gradient at layer i's output
        bias_grad = g.sum(0)
        for i in range(layers - 1, -1, -1):
            grads[:0] = [_weight_grad(g, hidden[i]) if need[1 + 2 * i] else None,
                         bias_grad if need[2 + 2 * i] else None]
            if i > 0:  # through layer i to its input, then through that input's ReLU (its bias gradient on the way)
                g = g @ weights[i]
                sums = g.new_zeros(sum_blocks(g.shape[0]), g.shape[1])
                if g.shape[0]:
                    run_parallel(relu_grad_rows, g.numpy(), hidden[i].numpy(), sums.numpy(),
                                 dtype_scalars(0, g.numpy().dtype), chunk=0)
                bias_grad = sums.sum(0)
        return (g @ weights[0] if need[0] else None, *grads)


def _weight_grad(g: Tensor, h: Tensor) -> Tensor:  # g [N, out], h [N, in] -> [out, in]
    """``g^T h``, formed as ``(h^T g)^T`` when ``g`` is the narrower: MKL runs ``[rows, N] x [N, cols]`` faster with
    the wider side as ``rows`` (32,768 rows: ``[16, N] x [N, 96]`` 1.41 ms, ``[96, N] x [N, 16]`` 0.95 ms)."""
    return (h.T @ g).T if g.shape[1] < h.shape[1] else g.T @ h


@numba.njit(parallel=True, **_JIT)
def bias_relu_rows(h, bias, zero):  # pragma: no cover - compiled
    """``h [N, C] = max(h + bias, 0)`` in place (``zero``: ``[0]`` in ``h``'s dtype)."""
    n, c = h.shape
    z = zero[0]
    for i in prange(n):
        for j in range(c):
            v = h[i, j] + bias[j]
            h[i, j] = v if v > 0 else z


@numba.njit(parallel=True, **_JIT)
def relu_grad_rows(g, h, sums, zero):  # pragma: no cover - compiled
    """``g [N, C]`` = ``g`` where ``h > 0``, else 0, in place (``h`` the ReLU's output); ``sums [B, C]``: the column
    sums of the result per block of :data:`SUM_BLOCK_ROWS` rows (``zero``: ``[0]`` in the dtype)."""
    n, c = g.shape
    z = zero[0]
    for b in prange(sums.shape[0]):
        for j in range(c):
            sums[b, j] = z
        for i in range(b * SUM_BLOCK_ROWS, min(n, (b + 1) * SUM_BLOCK_ROWS)):
            for j in range(c):
                v = g[i, j] if h[i, j] > 0 else z
                g[i, j] = v
                sums[b, j] += v
