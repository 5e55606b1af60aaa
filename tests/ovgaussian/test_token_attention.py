"""The adapter's row-loop attention (numba, forward and backward) against the torch elementwise reference."""

from __future__ import annotations

import pytest
import torch

from ovgaussian.model.token_attention import token_attention, token_attention_reference


def _inputs(n: int, t: int, h: int, d: int, dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, h, d, generator=g, dtype=dtype)
    k = torch.randn(n, t, h, d, generator=g, dtype=dtype)
    v = torch.randn(n, t, h, d, generator=g, dtype=dtype)
    if n > 2:
        k[0] *= 1e4  # a saturated softmax: one token takes all the weight
        q[1] = 0.0  # equal logits: uniform weights
        k[2, -1] = k[2, 0]  # two tokens tied for the maximum (one token: itself)
    return q, k, v


@pytest.mark.parametrize("n,t,h,d", [(0, 4, 4, 4), (1, 4, 4, 4), (300, 4, 4, 4), (40, 5, 3, 4), (57, 5, 2, 3),
                                     (9, 1, 1, 1)])
def test_token_attention_equals_the_reference_forward_and_backward(n, t, h, d):
    q, k, v = _inputs(n, t, h, d, torch.float64)
    upstream = torch.randn(n, h, d, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    results = []
    for fn in (token_attention, token_attention_reference):
        leaves = [x.clone().requires_grad_() for x in (q, k, v)]
        out = fn(*leaves)
        grads = torch.autograd.grad((out * upstream).sum(), leaves) if n else [torch.zeros_like(x) for x in leaves]
        results.append((out.detach(), grads))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-12, atol=1e-12)
    for a, b in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
        assert torch.isfinite(a).all()


def test_token_attention_float32_close_to_the_reference_and_gradcheck():
    q, k, v = _inputs(200, 4, 4, 4, torch.float32, seed=3)
    torch.testing.assert_close(token_attention(q, k, v), token_attention_reference(q, k, v), rtol=1e-5, atol=1e-5)
    for d in (3, 4):  # the generic kernels and the d = 4 ones
        small = [x[3:9].double().clone().requires_grad_() for x in _inputs(9, 4, 2, d, torch.float64, seed=4)]
        assert torch.autograd.gradcheck(token_attention, small)


def test_token_attention_refuses_mismatched_shapes():
    q, k, v = _inputs(4, 4, 4, 4, torch.float32)
    with pytest.raises(ValueError, match="token_attention"):
        token_attention(q[:, :2], k, v)
    with pytest.raises(ValueError, match="token_attention"):
        token_attention(q, k, v[:, :3])
