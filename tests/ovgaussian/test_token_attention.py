"""The adapter's row-loop attention (numba, forward and backward) against the torch elementwise reference."""

from __future__ import annotations

import pytest
import torch

from ovgaussian.model.token_attention import token_attention, token_attention_packed, token_attention_reference


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


@pytest.mark.parametrize("n,t,h,d", [(0, 4, 4, 4), (300, 4, 4, 4), (57, 5, 2, 3)])
def test_packed_keys_and_values_equal_the_separate_ones_forward_and_backward(n, t, h, d):
    """Keys and values as the two halves of one [N, T, 2, H, d] tensor, read and written in place by the kernels
    (the d = 4 ones and the generic ones): the output and every gradient equal the separate tensors' bitwise, and
    the reference's; the packed gradient holds the keys' and the values' gradients in its halves."""
    q, k, v = _inputs(n, t, h, d, torch.float64, seed=5)
    upstream = torch.randn(n, h, d, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    kv = torch.stack([k, v], dim=2).requires_grad_()
    qp = q.clone().requires_grad_()
    out = token_attention_packed(qp, kv)
    grads = torch.autograd.grad((out * upstream).sum(), [qp, kv]) if n else [torch.zeros_like(qp), torch.zeros_like(kv)]
    leaves = [x.clone().requires_grad_() for x in (q, k, v)]
    separate = token_attention(*leaves)
    want = torch.autograd.grad((separate * upstream).sum(), leaves) if n else [torch.zeros_like(x) for x in leaves]
    assert torch.equal(out, separate)
    assert torch.equal(grads[0], want[0]) and torch.equal(grads[1][:, :, 0], want[1])
    assert torch.equal(grads[1][:, :, 1], want[2])
    torch.testing.assert_close(out, token_attention_reference(q, k, v), rtol=1e-12, atol=1e-12)
    small = [q[3:9].clone().requires_grad_(), kv.detach()[3:9].clone().requires_grad_()] if n else None
    if small:
        assert torch.autograd.gradcheck(token_attention_packed, small)


def test_packed_attention_refuses_bad_shapes():
    q, k, v = _inputs(4, 4, 4, 4, torch.float32)
    with pytest.raises(ValueError, match="kv must be"):
        token_attention_packed(q, torch.stack([k, v, v], dim=2))
    with pytest.raises(ValueError, match="token_attention_packed"):
        token_attention_packed(q[:, :2], torch.stack([k, v], dim=2))
