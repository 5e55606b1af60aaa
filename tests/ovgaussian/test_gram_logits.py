"""The Gram-form text logits' hand-written backward against autograd on the same expression and on the direct
``compute_text_logits(phi(s))``, float64, with degenerate rows; and the eager row sum against the whole sum."""

from __future__ import annotations

import pytest
import torch

from ovgaussian.train import gram_logits, gram_rows
from ovgaussian.train.eager_rows import eager_row_sum
from ovgaussian.train.gram_logits import GramTerms, gram_terms, gram_text_logits, gram_text_logits_reference
from ovgaussian.train.losses import compute_text_logits, masked_cross_entropy
from seggaussian.core.constants import IGNORE_LABEL


def _phi(seed: int, hidden: int = 32, width: int = 48, dtype=torch.float64) -> torch.nn.Sequential:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(16, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, width)).to(dtype)


def _grads(logits_fn, phi, semantic, text, upstream):
    s = semantic.clone().requires_grad_()
    out = logits_fn(s)
    grads = torch.autograd.grad((out * upstream).sum(), [s, *phi.parameters()])
    return out.detach(), grads


def _degenerate_rows(semantic: torch.Tensor, phi) -> torch.Tensor:
    semantic = semantic.clone()
    semantic[:3] = 0.0  # hidden = relu(b1)
    # rows whose every pre-activation is negative: hidden = 0, phi(s) = b2
    w1, b1 = phi[0].weight.detach(), phi[0].bias.detach()
    direction = torch.linalg.lstsq(w1, -(b1.abs() + 1.0)[:, None]).solution[:, 0]
    semantic[3] = 50.0 * direction / direction.norm()
    semantic[4] = 1e-30  # tiny values
    semantic[5] = 1e6  # huge values
    return semantic


@pytest.fixture(params=["numba", "torch"])
def row_passes(request, monkeypatch):
    """Both forms of the row passes: the numba loops (CPU float tensors) and the torch expressions (other devices)."""
    if request.param == "torch":
        monkeypatch.setattr(gram_logits, "_fused_rows", lambda tensor: False)
    return request.param


@pytest.mark.parametrize("seed", [0, 1])
def test_gram_logits_equal_autograd_and_the_direct_expression_forward_and_backward(seed, row_passes):
    phi = _phi(seed)
    text = torch.randn(7, 48, dtype=torch.float64)
    semantic = _degenerate_rows(torch.randn(200, 16, dtype=torch.float64), phi)
    upstream = torch.randn(200, 7, dtype=torch.float64)
    fast = _grads(lambda s: gram_text_logits(s, gram_terms(phi, text), 0.07), phi, semantic, text, upstream)
    reference = _grads(lambda s: gram_text_logits_reference(s, gram_terms(phi, text), 0.07), phi, semantic, text,
                       upstream)
    direct = _grads(lambda s: compute_text_logits(phi(s), text, 0.07), phi, semantic, text, upstream)
    for other in (reference, direct):
        torch.testing.assert_close(fast[0], other[0], rtol=1e-9, atol=1e-9)
        for a, b in zip(fast[1], other[1]):
            torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9 * max(1.0, float(b.abs().max())))
    assert all(torch.isfinite(g).all() for g in fast[1])


def test_gram_logits_gradcheck_and_a_zero_norm_row(row_passes):
    """gradcheck of the Function in every input; a row whose phi(s) is exactly zero (b2 = 0, hidden = 0) gets the
    direct expression's value (0) and gradient (the norm's clamp passes none), not NaN."""
    phi = _phi(2, hidden=6, width=5)
    text = torch.randn(3, 5, dtype=torch.float64)
    terms = gram_terms(phi, text)
    inputs = [torch.randn(9, 16, dtype=torch.float64), *(t.detach().clone() for t in terms)]
    inputs = [x.requires_grad_() for x in inputs]
    assert torch.autograd.gradcheck(lambda s, *t: gram_text_logits(s, GramTerms(*t), 0.3), inputs)

    with torch.no_grad():
        phi[2].bias.zero_()
        phi[0].bias.fill_(-1.0)
    s = torch.zeros(2, 16, dtype=torch.float64, requires_grad=True)
    out = gram_text_logits(s, gram_terms(phi, text), 0.3)
    assert torch.equal(out.detach(), torch.zeros(2, 3, dtype=torch.float64))
    (g_fast,) = torch.autograd.grad(out.sum(), [s])
    s2 = s.detach().clone().requires_grad_()
    (g_direct,) = torch.autograd.grad(compute_text_logits(phi(s2), text, 0.3).sum(), [s2])
    assert torch.equal(g_fast, g_direct)


def test_gram_logits_refuse_a_bad_temperature_and_accept_no_rows():
    phi = _phi(3)
    text = torch.randn(4, 48, dtype=torch.float64)
    with pytest.raises(ValueError, match="temperature"):
        gram_text_logits(torch.randn(2, 16, dtype=torch.float64), gram_terms(phi, text), 0.0)
    empty = torch.zeros(0, 16, dtype=torch.float64, requires_grad=True)
    out = gram_text_logits(empty, gram_terms(phi, text), 0.1)
    assert out.shape == (0, 4)
    out.sum().backward()
    assert empty.grad.shape == (0, 16)


def test_numba_row_passes_match_the_torch_ones_in_float32_over_several_sum_blocks(monkeypatch):
    """float32 (what training runs), more rows than one block of the backward's column sums, a short last block,
    rows whose hidden layer is all zero: the numba passes give the torch expressions' values and gradients; and the
    same bits on one thread as on two (the block sums are added in a fixed order)."""
    import numba

    phi = _phi(6, hidden=128, width=384, dtype=torch.float32)
    text = torch.randn(20, 384)
    rows = 2 * gram_rows.SUM_BLOCK_ROWS + 77
    semantic = _degenerate_rows(torch.randn(rows, 16), phi)
    semantic[4:6] = torch.randn(2, 16)  # drop the 1e-30 / 1e6 rows: float32 products of 1e6 lose the comparison
    upstream = torch.randn(rows, 20)

    def run():
        return _grads(lambda s: gram_text_logits(s, gram_terms(phi, text), 0.07), phi, semantic, text, upstream)

    fused = run()
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = run()
    finally:
        numba.set_num_threads(threads)
    assert torch.equal(fused[0], single[0]) and all(torch.equal(a, b) for a, b in zip(fused[1], single[1]))
    monkeypatch.setattr(gram_logits, "_fused_rows", lambda tensor: False)
    plain = run()
    torch.testing.assert_close(fused[0], plain[0], rtol=1e-5, atol=1e-5)
    for a, b in zip(fused[1], plain[1]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))


def test_gram_terms_only_for_linear_relu_linear():
    text = torch.randn(4, 48)
    assert gram_terms(torch.nn.Sequential(torch.nn.Linear(16, 48)), text) is None
    no_bias = torch.nn.Sequential(torch.nn.Linear(16, 8), torch.nn.ReLU(), torch.nn.Linear(8, 48, bias=False))
    assert gram_terms(no_bias, text) is None
    terms = gram_terms(_phi(4, dtype=torch.float32), text)
    assert torch.equal(terms.gram, terms.gram.T)


@pytest.mark.parametrize("chunk_rows", [1, 37, 64, 1000])
def test_eager_row_sum_equals_the_whole_sum_forward_and_backward(chunk_rows):
    """Chunks (the last one short), an int row tensor, a parameter that no chunk uses, and rows that need no
    gradient: the value and every gradient equal those of fn on the whole rows; the backward scales by the
    incoming gradient."""
    torch.manual_seed(5)
    phi = _phi(5)
    text = torch.randn(6, 48, dtype=torch.float64)
    semantic = torch.randn(150, 16, dtype=torch.float64)
    labels = torch.randint(0, 6, (150,))
    labels[::7] = IGNORE_LABEL  # rows that add no term (whole chunks of them when chunk_rows is 1)
    unused = torch.randn(3, dtype=torch.float64, requires_grad=True)

    def fn(rows, rows_labels, *params):
        terms = GramTerms(*params[:-1])
        mean, count = masked_cross_entropy(gram_text_logits(rows, terms, 0.1), rows_labels)
        return mean * count

    def run(chunks):
        s = semantic.clone().requires_grad_()
        terms = gram_terms(phi, text)
        total = eager_row_sum(fn, (s, labels), (*terms, unused), chunk_rows=chunks, min_rows=0)
        grads = torch.autograd.grad(3.0 * total, [s, *phi.parameters(), unused], allow_unused=True)
        return total.detach(), grads

    whole, chunked = run(10_000), run(chunk_rows)
    torch.testing.assert_close(chunked[0], whole[0], rtol=1e-12, atol=1e-12)
    for a, b in zip(chunked[1][:-1], whole[1][:-1]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert whole[1][-1] is None  # one piece: autograd's "unused"; in chunks: an explicit zero gradient
    zero = torch.zeros(3, dtype=torch.float64)
    assert chunked[1][-1] is None if chunk_rows >= 150 else torch.equal(chunked[1][-1], zero)

    with torch.no_grad():  # evaluation: the plain sum, no gradients taken
        assert torch.equal(eager_row_sum(fn, (semantic, labels), (*gram_terms(phi, text), unused),
                                         chunk_rows=chunk_rows, min_rows=0), whole[0])


def test_eager_row_sum_refuses_mismatched_rows():
    with pytest.raises(ValueError, match="rows"):
        eager_row_sum(lambda a, b: a.sum(), (torch.zeros(3), torch.zeros(4)), (), chunk_rows=1, min_rows=0)
