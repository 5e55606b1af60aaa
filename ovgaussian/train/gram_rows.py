"""The elementwise row passes of the Gram-form text logits (``ovgaussian.train.gram_logits``) as numba loops.

Between its products, the Gram form's forward and backward are elementwise work on ``[N, H]`` rows (``H = 128``):
adding ``c`` to ``h G``, the row sums ``h . (h G + c)``, the ReLU's mask, scaling rows by ``dn2``, the column sums
of the bias gradients. As torch operations each is a pass over 16 MB per 32,768 rows (more than the cache holds),
about 15 ms of a 98 ms eager chunk by ``torch.profiler``, which overstates small operations: with these loops the
chunk took 4.9 ms less (median of 15 alternated runs). Here each direction is one loop over the rows, called through
``run_parallel``:

- :func:`forward_rows`: ``half_grad = h G + c`` in place, ``n2 = h . half_grad + h . c + bb``, the norms, the scale
  ``1 / (max(norm, eps) T)`` and the logits ``(h A + tb) * scale``; ``h G``, ``h A`` and ``h . c`` come from one
  product ``h [G | A | c | 0]`` (:func:`product_width`);
- :func:`logit_grad_rows`: ``grad_dots = g * scale`` and ``dn2`` from the logits' gradient ``g`` (``[N, C]``);
- :func:`backward_rows`: ``dh = (h > 0) * (pre + 2 dn2 half_grad)`` in place of ``pre = grad_dots A^T``,
  ``weighted = dn2 h``, and the column sums of both (per block of rows, added in a fixed order: deterministic).

The torch expressions they replace stay in ``gram_logits`` as the path for other devices and dtypes; the tests
compare both, forward and backward, on degenerate rows too. CPU float32 and float64 tensors only.
"""

from __future__ import annotations

import math

import numba
from numba import prange

from seggaussian.render.parallel import SUM_BLOCK_ROWS

#: The forward's product ``h [G | A | c]`` gets zero columns up to a multiple of this (:func:`product_width`).
PRODUCT_COLUMNS_MULTIPLE = 16

#: ``reassoc`` lets the row sums run on SIMD lanes; no flag that assumes finite values or approximates a division.
_JIT = dict(cache=True, nogil=True, fastmath={"reassoc", "contract"})


@numba.njit(parallel=True, **_JIT)
def forward_rows(hidden, products, bias_hidden, text_bias, bias_square, eps, temperature,
                 logits, scale, roots):  # pragma: no cover - compiled
    """From ``hidden [N, H]`` and ``products [N, >= H + C + 1] = h [G | A | c | 0]``: ``products[:, :H] += c`` in
    place (the backward's ``half_grad``), ``logits [N, C]``, ``scale [N]``, ``roots [N]`` (``sqrt(max(n2, 0))``)."""
    n, h = hidden.shape
    c = text_bias.shape[0]
    bb, ep, temp = bias_square[0], eps[0], temperature[0]
    for i in prange(n):
        acc = bb - bb
        for j in range(h):
            v = products[i, j] + bias_hidden[j]
            products[i, j] = v
            acc += hidden[i, j] * v
        squared = acc + products[i, h + c] + bb
        root = math.sqrt(max(squared, bb - bb))
        roots[i] = root
        s = 1 / (max(root, ep) * temp)
        scale[i] = s
        for k in range(c):
            logits[i, k] = (products[i, h + k] + text_bias[k]) * s


@numba.njit(parallel=True, **_JIT)
def logit_grad_rows(grad_logits, logits, scale, roots, eps, grad_dots, grad_squared):  # pragma: no cover - compiled
    """``grad_dots [N, C] = g * scale`` and ``grad_squared [N]``: ``-(g . logits) / max(norm, eps)`` through
    ``d norm / d n2 = 1 / max(2 norm, eps)``, 0 where a clamp blocks it (``n2 < 0`` or ``norm < eps``)."""
    n, c = grad_logits.shape
    ep = eps[0]
    for i in prange(n):
        s = scale[i]
        acc = s - s
        for k in range(c):
            g = grad_logits[i, k]
            grad_dots[i, k] = g * s
            acc += g * logits[i, k]
        root = roots[i]
        # roots = sqrt(max(n2, 0)) >= eps > 0 implies n2 > 0: the one test covers both clamps
        grad_squared[i] = -acc / max(root, ep) / max(2 * root, ep) if root >= ep else s - s


@numba.njit(parallel=True, **_JIT)
def backward_rows(hidden, products, grad_squared, grad_hidden, weighted, grad_sums, weighted_sums
                  ):  # pragma: no cover - compiled
    """In place ``grad_hidden [N, H]`` (holding ``grad_dots A^T``) = ``(h > 0) * (it + 2 dn2 half_grad)`` (``half_grad
    = products[:, :H]``); ``weighted [N, H] = dn2 h``; ``grad_sums``, ``weighted_sums [B, H]``: their column sums per
    block of :data:`SUM_BLOCK_ROWS` rows."""
    n, h = hidden.shape
    blocks = grad_sums.shape[0]
    for b in prange(blocks):
        for j in range(h):
            grad_sums[b, j] = 0
            weighted_sums[b, j] = 0
        for i in range(b * SUM_BLOCK_ROWS, min(n, (b + 1) * SUM_BLOCK_ROWS)):
            d = grad_squared[i]
            two_d = 2 * d
            for j in range(h):
                x = hidden[i, j]
                g = grad_hidden[i, j] + two_d * products[i, j] if x > 0 else x - x
                grad_hidden[i, j] = g
                grad_sums[b, j] += g
                w = x * d
                weighted[i, j] = w
                weighted_sums[b, j] += w


def product_width(hidden: int, classes: int) -> int:
    """Columns of the forward's product ``h [G | A | c | 0]``: ``H + C + 1`` rounded up to a multiple of
    :data:`PRODUCT_COLUMNS_MULTIPLE` (zero columns): a ``[32768, 128] x [128, 149]`` product took 14.0 ms where
    ``[128, 160]`` took 8.8 ms and the separate ``[128, 128]`` and ``[128, 21]`` ones 9.8 ms together."""
    width = hidden + classes + 1
    return -(-width // PRODUCT_COLUMNS_MULTIPLE) * PRODUCT_COLUMNS_MULTIPLE
