"""Cosine text logits of the decoder ``phi = Linear o ReLU o Linear`` in Gram form, with a hand-written backward.

For ``phi(s) = W2 relu(W1 s + b1) + b2`` (``W1 [H, S]``, ``W2 [D, H]``), hidden rows ``h = relu(W1 s + b1)`` and
unit text rows ``t [C, D]``, the logits ``cos(phi(s), t) / T`` need only ``H``-wide products (``H = 128`` against
``D = 384``):

    dots  = h A + tb                      A = W2^T t^T [H, C],  tb = t b2 [C]
    n2    = h G h^T + 2 h c + bb           G = W2^T W2 [H, H] (symmetric),  c = W2^T b2 [H],  bb = |b2|^2
    logit = dots / max(sqrt(max(n2, 0)), COSINE_NORM_EPS) / T

:func:`gram_terms` builds ``(W1, b1, G, A, c, tb, bb)`` once per loss with autograd (small ``[H, H]`` products);
:func:`gram_text_logits` applies them to a chunk of rows through :class:`_GramTextLogits`, whose backward uses
``G``'s symmetry: ``d(h G h^T)/dh = 2 h G``, the product the forward already made, so forward and backward cost
two ``[N, H] x [H, H]`` products (``h G``, and ``G``'s gradient ``h^T diag(dn2) h``) where autograd's graph of the
same expression costs three (plus ``G^T`` times the product's gradient), and no elementwise pass is recorded.
With ``ovgaussian.train.eager_rows`` (no recomputation) the 3D text loss costs those two per chunk; under activation
checkpointing it was four. On CPU float tensors the elementwise work between the products is one numba loop over the
rows per direction (``ovgaussian.train.gram_rows``); elsewhere it is the torch expressions. The autograd expression
it replaces is kept as :func:`gram_text_logits_reference`; the tests compare all three (and the direct
``compute_text_logits(phi(s))``), forward and backward, on degenerate rows too.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ovgaussian.train import gram_rows
from ovgaussian.train.losses import COSINE_NORM_EPS, normalize_rows
from seggaussian.render.parallel import dtype_scalars, run_parallel, sum_blocks


class GramTerms(NamedTuple):
    """The per-loss constants of the Gram form (module docstring), each still attached to ``phi``'s parameters."""

    w1: Tensor  # [H, S] first layer's weight
    b1: Tensor  # [H] first layer's bias
    gram: Tensor  # [H, H] W2^T W2, exactly symmetric
    text_hidden: Tensor  # [H, C] W2^T t^T
    bias_hidden: Tensor  # [H] W2^T b2
    text_bias: Tensor  # [C] t b2
    bias_square: Tensor  # [] |b2|^2


def is_gram_decoder(phi) -> bool:
    """Whether ``phi`` has the form the Gram terms need: ``Sequential(Linear, ReLU, Linear with bias)``."""
    layers = list(phi) if isinstance(phi, torch.nn.Sequential) else []
    return (len(layers) == 3 and isinstance(layers[0], torch.nn.Linear) and isinstance(layers[1], torch.nn.ReLU)
            and isinstance(layers[2], torch.nn.Linear) and layers[2].bias is not None)


def gram_terms(phi, text_embeddings: Tensor) -> GramTerms | None:  # text_embeddings [C, D]
    """:class:`GramTerms` of ``phi`` (:func:`is_gram_decoder`) and the text rows (made unit here); None for any other
    ``phi`` (callers then take the direct expression)."""
    if not is_gram_decoder(phi):
        return None
    first, last = phi[0], phi[2]
    b1 = first.bias if first.bias is not None else first.weight.new_zeros(first.weight.shape[0])
    w2, b2 = last.weight, last.bias  # [D, H], [D]
    text = normalize_rows(text_embeddings)  # [C, D]
    gram = w2.T @ w2
    gram = 0.5 * (gram + gram.T)  # exactly symmetric, which the backward's 2 h G relies on
    return GramTerms(first.weight, b1, gram, w2.T @ text.T, w2.T @ b2, text @ b2, b2.square().sum())


def gram_text_logits(semantic: Tensor, terms: GramTerms, temperature: float) -> Tensor:  # [N, S] -> [N, C]
    """``cos(phi(semantic), t) / temperature`` from :func:`gram_terms` (module docstring)."""
    if temperature <= 0:
        raise ValueError(f"temperature must be positive, got {temperature}")
    return _GramTextLogits.apply(semantic, *terms, float(temperature))


def gram_text_logits_reference(semantic: Tensor, terms: GramTerms, temperature: float) -> Tensor:
    """The same logits as one autograd expression (the form training used before the hand-written backward)."""
    if temperature <= 0:
        raise ValueError(f"temperature must be positive, got {temperature}")
    hidden = torch.relu(semantic @ terms.w1.T + terms.b1)
    dots = hidden @ terms.text_hidden + terms.text_bias[None, :]
    squared = ((hidden @ terms.gram) * hidden).sum(1) + 2.0 * (hidden @ terms.bias_hidden) + terms.bias_square
    norms = squared.clamp_min(0.0).sqrt().clamp_min(COSINE_NORM_EPS)
    return dots / norms[:, None] / temperature


class _GramTextLogits(torch.autograd.Function):
    @staticmethod
    def forward(ctx, semantic, w1, b1, gram, text_hidden, bias_hidden, text_bias, bias_square,  # noqa: D102
                temperature):
        hidden = torch.addmm(b1, semantic, w1.T).clamp_min_(0.0)  # [N, H] relu
        if _fused_rows(hidden):  # the row passes in one numba loop (ovgaussian.train.gram_rows)
            # h [G | A | c | 0] in one product; its first H columns become half_grad = h G + c in the loop
            (n, h), c = hidden.shape, text_hidden.shape[1]
            right = gram.new_zeros(h, gram_rows.product_width(h, c))
            right[:, :h], right[:, h:h + c], right[:, h + c] = gram, text_hidden, bias_hidden
            half_grad = hidden @ right
            dtype = hidden.numpy().dtype
            logits, scale, roots = hidden.new_empty(n, c), hidden.new_empty(n), hidden.new_empty(n)
            if n:
                run_parallel(gram_rows.forward_rows, hidden.numpy(), half_grad.numpy(),
                             bias_hidden.detach().contiguous().numpy(), text_bias.detach().contiguous().numpy(),
                             dtype_scalars(float(bias_square), dtype), dtype_scalars(COSINE_NORM_EPS, dtype),
                             dtype_scalars(temperature, dtype), logits.numpy(), scale.numpy(), roots.numpy(), chunk=0)
            live = None  # marks the fused forward: its backward is fused too (the gradient has the logits' device)
        else:
            half_grad = (hidden @ gram).add_(bias_hidden)  # [N, H] h G + c: half of d n2 / dh (G symmetric)
            squared = (hidden * half_grad).sum(1).add_(hidden @ bias_hidden).add_(bias_square)  # h G h^T + 2 h c + bb
            roots = squared.clamp_min(0.0).sqrt_()
            scale = roots.clamp_min(COSINE_NORM_EPS).mul_(temperature).reciprocal_()  # 1 / (norm T)
            logits = torch.addmm(text_bias, hidden, text_hidden).mul_(scale[:, None])
            # the norm's gradient flows where both clamps pass it (as autograd's clamp_min: input >= bound)
            live = (squared >= 0.0) & (roots >= COSINE_NORM_EPS)
        ctx.save_for_backward(semantic, w1, text_hidden, hidden, half_grad, logits, scale, roots, live)
        return logits

    @staticmethod
    def backward(ctx, grad_logits):  # noqa: D102
        semantic, w1, text_hidden, hidden, half_grad, logits, scale, roots, live = ctx.saved_tensors
        need = ctx.needs_input_grad
        grad_logits = grad_logits.contiguous()
        if live is None:
            return _fused_backward(need, grad_logits, semantic, w1, text_hidden, hidden, half_grad, logits, scale,
                                   roots)
        grad_dots = grad_logits * scale[:, None]  # [N, C]
        # logit = dot / (norm T): d/dnorm = -logit / norm; norm = sqrt(n2): d/dn2 = 1 / (2 norm)
        grad_norm = (grad_logits * logits).sum(1).neg_() / roots.clamp_min(COSINE_NORM_EPS)
        grad_squared = torch.where(live, grad_norm / (2.0 * roots).clamp_min(COSINE_NORM_EPS), 0.0)  # [N]
        grad_gram = grad_bias_hidden = None
        if need[3] or need[5]:
            weighted = hidden * grad_squared[:, None]  # [N, H] diag(dn2) h
            grad_gram = weighted.T @ hidden if need[3] else None  # h^T diag(dn2) h, symmetric
            grad_bias_hidden = 2.0 * weighted.sum(0) if need[5] else None
        grad_text_hidden = hidden.T @ grad_dots if need[4] else None
        grad_text_bias = grad_dots.sum(0) if need[6] else None
        grad_bias_square = grad_squared.sum() if need[7] else None
        # dh = grad_dots A^T + dn2 (2 h G + 2 c), then the ReLU's mask (h > 0)
        grad_hidden = torch.addmm(half_grad * (2.0 * grad_squared)[:, None], grad_dots, text_hidden.T)
        # ReLU's own backward op (grad where h > 0): one pass, where masked_fill_ with a [N, H] mask took ~10x longer
        grad_hidden = torch.ops.aten.threshold_backward(grad_hidden, hidden, 0.0)
        return (grad_hidden @ w1 if need[0] else None,
                grad_hidden.T @ semantic if need[1] else None,
                grad_hidden.sum(0) if need[2] else None,
                grad_gram, grad_text_hidden, grad_bias_hidden, grad_text_bias, grad_bias_square, None)


def _fused_rows(tensor: Tensor) -> bool:
    """Whether the numba row passes apply: a CPU float32 / float64 tensor."""
    return tensor.device.type == "cpu" and tensor.dtype in (torch.float32, torch.float64)


def _fused_backward(need, grad_logits, semantic, w1, text_hidden, hidden, products, logits, scale, roots):
    """:meth:`_GramTextLogits.backward` with its row passes in numba (``ovgaussian.train.gram_rows``); the first ``H``
    columns of the forward's ``products`` hold ``half_grad``."""
    n, dtype = hidden.shape[0], hidden.numpy().dtype
    grad_dots, grad_squared = torch.empty_like(grad_logits), hidden.new_empty(n)
    blocks = sum_blocks(n)
    grad_sums, weighted_sums = hidden.new_zeros(blocks, hidden.shape[1]), hidden.new_zeros(blocks, hidden.shape[1])
    weighted = torch.empty_like(hidden)  # [N, H] diag(dn2) h
    if n:
        run_parallel(gram_rows.logit_grad_rows, grad_logits.numpy(), logits.numpy(), scale.numpy(), roots.numpy(),
                     dtype_scalars(COSINE_NORM_EPS, dtype), grad_dots.numpy(), grad_squared.numpy(), chunk=0)
    # A^T made contiguous first: with a transposed [C, H] operand the product took 2-5 ms instead of 1.2 (C = 20)
    grad_hidden = grad_dots @ text_hidden.T.contiguous()  # [N, H] grad_dots A^T, made dh in the loop
    if n:
        run_parallel(gram_rows.backward_rows, hidden.numpy(), products.numpy(), grad_squared.numpy(),
                     grad_hidden.numpy(), weighted.numpy(), grad_sums.numpy(), weighted_sums.numpy(), chunk=0)
    return (grad_hidden @ w1 if need[0] else None,
            grad_hidden.T @ semantic if need[1] else None,
            grad_sums.sum(0) if need[2] else None,
            weighted.T @ hidden if need[3] else None,  # h^T diag(dn2) h, symmetric
            hidden.T @ grad_dots if need[4] else None,
            2.0 * weighted_sums.sum(0) if need[5] else None,
            grad_dots.sum(0) if need[6] else None,
            grad_squared.sum() if need[7] else None,
            None)
