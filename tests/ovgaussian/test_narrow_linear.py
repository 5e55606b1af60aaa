"""narrow_linear equals F.linear, values and every gradient, with and without a bias, and on no rows."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from ovgaussian.model.narrow_linear import narrow_linear


@pytest.mark.parametrize("rows", [0, 1, 300])
@pytest.mark.parametrize("with_bias", [True, False])
def test_narrow_linear_equals_f_linear_forward_and_backward(rows, with_bias):
    g = torch.Generator().manual_seed(rows)
    x = torch.randn(rows, 11, generator=g, dtype=torch.float64)
    weight = torch.randn(64, 11, generator=g, dtype=torch.float64)
    bias = torch.randn(64, generator=g, dtype=torch.float64) if with_bias else None
    upstream = torch.randn(rows, 64, generator=g, dtype=torch.float64)
    results = []
    for fn in (narrow_linear, F.linear):
        leaves = [t.clone().requires_grad_() for t in (x, weight) + ((bias,) if with_bias else ())]
        out = fn(leaves[0], leaves[1], leaves[2] if with_bias else None)
        results.append((out.detach(), torch.autograd.grad((out * upstream).sum(), leaves)))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-13, atol=1e-13)
    for a, b in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_narrow_linear_gradcheck_and_shape_check():
    leaves = [torch.randn(5, 3, dtype=torch.float64, requires_grad=True),
              torch.randn(4, 3, dtype=torch.float64, requires_grad=True),
              torch.randn(4, dtype=torch.float64, requires_grad=True)]
    assert torch.autograd.gradcheck(narrow_linear, leaves)
    with pytest.raises(ValueError, match="narrow_linear"):
        narrow_linear(torch.zeros(5, 4), torch.zeros(4, 3))
