"""The adapter MLP's fused bias + ReLU passes (numba) against the nn.Sequential they replace, forward and backward."""

from __future__ import annotations

import numba
import pytest
import torch
from torch import nn

from ovgaussian.model import relu_mlp as relu_mlp_module
from ovgaussian.model.relu_mlp import relu_mlp


def _mlp(widths, dtype, seed=0) -> nn.Sequential:
    torch.manual_seed(seed)
    layers: list[nn.Module] = []
    for i in range(len(widths) - 1):
        layers.append(nn.Linear(widths[i], widths[i + 1]))
        if i < len(widths) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers).to(dtype)


def _run(fn, mlp, x, upstream):
    leaf = x.clone().requires_grad_()
    out = fn(mlp, leaf)
    grads = torch.autograd.grad((out * upstream).sum(), [leaf, *mlp.parameters()]) if len(x) else None
    return out.detach(), grads


@pytest.mark.parametrize("rows", [0, 1, 37, 2 * relu_mlp_module.SUM_BLOCK_ROWS + 5])
@pytest.mark.parametrize("widths", [(27, 96, 96, 16), (5, 7, 3), (4, 6)])
def test_relu_mlp_equals_the_sequential_forward_and_backward(rows, widths):
    """float64; rows whose pre-activations are all negative (ReLU closed), zero rows, huge and tiny values; several
    blocks of the bias gradient's column sums; a single Linear (no ReLU)."""
    mlp = _mlp(widths, torch.float64)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(rows, widths[0], generator=g, dtype=torch.float64)
    if rows > 4:
        x[0] = 0.0
        x[1] = -1e3 * torch.sign(mlp[0].weight.detach().sum(0))  # mostly negative pre-activations
        x[2] *= 1e-30
        x[3] *= 1e6
    upstream = torch.randn(rows, widths[-1], generator=g, dtype=torch.float64)
    fast, reference = _run(relu_mlp, mlp, x, upstream), _run(lambda m, v: m(v), mlp, x, upstream)
    torch.testing.assert_close(fast[0], reference[0], rtol=1e-12, atol=1e-9)
    if rows:
        for a, b in zip(fast[1], reference[1]):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-9 * max(1.0, float(b.abs().max())))
    else:
        assert fast[0].shape == (0, widths[-1])


def test_relu_mlp_float32_gradcheck_and_threads():
    """float32 close to the Sequential; gradcheck in float64; the same bits on one thread as on two."""
    mlp = _mlp((27, 96, 96, 16), torch.float32, seed=2)
    x = torch.randn(3000, 27)
    upstream = torch.randn(3000, 16)
    fast, reference = _run(relu_mlp, mlp, x, upstream), _run(lambda m, v: m(v), mlp, x, upstream)
    torch.testing.assert_close(fast[0], reference[0], rtol=1e-5, atol=1e-5)
    for a, b in zip(fast[1], reference[1]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = _run(relu_mlp, mlp, x, upstream)
    finally:
        numba.set_num_threads(threads)
    assert torch.equal(single[0], fast[0]) and all(torch.equal(a, b) for a, b in zip(single[1], fast[1]))

    params = [p.detach().clone().requires_grad_() for p in _mlp((3, 4, 2), torch.float64, seed=3).parameters()]
    inputs = [torch.randn(6, 3, dtype=torch.float64, requires_grad=True), *params]
    assert torch.autograd.gradcheck(relu_mlp_module._ReluMLP.apply, inputs)


def test_other_layouts_run_the_sequential():
    """A Sequential that is not Linear (ReLU Linear)*, or a Linear without bias: the module itself runs."""
    calls = []

    class Counting(nn.Sequential):
        def forward(self, x):
            calls.append(1)
            return super().forward(x)

    x = torch.randn(5, 4)
    for mlp in (Counting(nn.Linear(4, 3), nn.Tanh(), nn.Linear(3, 2)), Counting(nn.Linear(4, 3, bias=False)),
                Counting(nn.Linear(4, 3), nn.ReLU())):
        calls.clear()
        torch.testing.assert_close(relu_mlp(mlp, x), nn.Sequential.forward(mlp, x))
        assert calls == [1]
    fused = Counting(nn.Linear(4, 3), nn.ReLU(), nn.Linear(3, 2))
    calls.clear()
    relu_mlp(fused, x)
    assert calls == []


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_first_layer_override_equals_linear_then_the_rest(dtype):
    """``first=(w, b)`` replaces the first layer (the adapter folds its output projection into it): values and the
    gradients of x, of the tensors w and b were computed from, and of the other layers, against
    ``mlp[1:](F.linear(x, w, b))``; float64 takes the numba passes, float16 the Sequential fallback."""
    mlp = _mlp((32, 96, 96, 16), torch.float64, seed=4).to(dtype)
    g = torch.Generator().manual_seed(5)
    x = torch.randn(300, 32, generator=g, dtype=torch.float64).to(dtype)
    upstream = torch.randn(300, 16, generator=g, dtype=torch.float64).to(dtype)
    fold = torch.randn(32, 32, generator=g, dtype=torch.float64).to(dtype).requires_grad_()

    def run(fn):
        leaf = x.clone().requires_grad_()
        first = (mlp[0].weight @ fold, mlp[0].bias * 2)
        out = fn(leaf, first)
        return out.detach(), torch.autograd.grad((out * upstream).sum(), [leaf, fold, *mlp.parameters()])

    fast = run(lambda v, first: relu_mlp(mlp, v, first=first))
    reference = run(lambda v, first: mlp[1:](torch.nn.functional.linear(v, *first)))
    tol = dict(rtol=1e-10, atol=1e-9) if dtype == torch.float64 else dict(rtol=0, atol=0)
    torch.testing.assert_close(fast[0], reference[0], **tol)
    for a, b in zip(fast[1], reference[1]):
        torch.testing.assert_close(a, b, **(tol if dtype != torch.float64 else
                                            dict(rtol=1e-10, atol=1e-9 * max(1.0, float(b.abs().max())))))
    assert float(fast[1][1].abs().sum()) > 0  # the gradient reaches what the override was computed from
