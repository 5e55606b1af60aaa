"""Training losses of OVGaussian (paper eq. 3-5).

- Text alignment (3D-to-text on Gaussians, 2D-to-text on rendered pixels): cross-entropy of
  ``logits = cos(phi(x), e_m) / temperature`` over the seen classes' text embeddings ``e_m``,
  averaged over the elements whose label is not ``IGNORE_LABEL``.
- Transductive variant (``LossConfig.unlabelled_as_unseen``): the elements without a seen-class label take the
  partial-label term ``-log sum_u p_u`` over the unseen classes' columns (:func:`text_cross_entropy`).
- Visual-semantic alignment: ``1 - cos(psi(M), teacher)`` averaged over valid pixels.
- ``L = L_3d + L_2d + w * L_cosine``; ``no_3dt_align`` drops L_3d, ``no_vs_align`` drops L_cosine.
- Optional IoU surrogate (``LossConfig.lovasz_weight``): the Lovasz-softmax loss (Berman, Rannen Triki and
  Blaschko, CVPR 2018) of the 3D text logits, added to L_3d. It is the convex (Lovasz) extension of the Jaccard
  loss ``1 - IoU`` of each class present in the scene's labels, so a false positive costs what it costs the
  benchmark's mIoU (a class with few Gaussians pays for every row of another class it takes).

Means (not the paper's sums) keep the loss scale independent of scene and image size. Every loss
of an empty valid set is an exact 0 that stays attached to the graph (zero, finite gradients), never NaN.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from seggaussian.core.constants import IGNORE_LABEL

#: Lower bound of a vector norm in cosine similarities: a zero vector has cosine 0, not NaN.
COSINE_NORM_EPS = 1e-8


class LossTerms(NamedTuple):
    """Loss of one scene/view (or a batch).

    Fields:
        total: scalar the optimizer minimizes.
        text_3d: 3D-to-text cross-entropy (0 when switched off or no labelled Gaussian).
        text_2d: 2D-to-text cross-entropy (0 when no labelled pixel).
        cosine: visual-semantic cosine loss (0 when switched off, no teacher or no valid pixel).
        count_3d, count_2d, count_cosine: elements each term averaged over.
    """

    total: torch.Tensor
    text_3d: torch.Tensor
    text_2d: torch.Tensor
    cosine: torch.Tensor
    count_3d: int
    count_2d: int
    count_cosine: int


def normalize_rows(x: torch.Tensor) -> torch.Tensor:
    """Rows of ``x [..., D]`` at unit norm (zero rows stay zero)."""
    return x / x.norm(dim=-1, keepdim=True).clamp_min(COSINE_NORM_EPS)


def compute_text_logits(
    features: torch.Tensor,  # [P, D] decoder outputs phi(.)
    text_embeddings: torch.Tensor,  # [C, D] seen-class text embeddings
    temperature: float,
) -> torch.Tensor:  # [P, C]
    """Cosine similarity to each class embedding divided by the temperature."""
    if temperature <= 0:
        raise ValueError(f"temperature must be positive, got {temperature}")
    return normalize_rows(features) @ normalize_rows(text_embeddings).T / temperature


def masked_cross_entropy(
    logits: torch.Tensor,  # [P, C]
    labels: torch.Tensor,  # [P] int, class index in 0..C-1 or IGNORE_LABEL
    class_weights: torch.Tensor | None = None,  # [C] weight of each class's rows; None: all 1
    row_weights: torch.Tensor | None = None,  # [P] weight of each row; None: all 1
) -> tuple[torch.Tensor, int]:
    """Mean cross-entropy over labelled rows (log-softmax, stable for any finite logits) and their count.

    With ``class_weights`` each row's term is multiplied by its class's weight and the sum is still divided
    by the row count (weights normalized over the training data keep the loss on the same scale); with
    ``row_weights`` (``LossConfig.opacity_power``) each term is also multiplied by its row's weight."""
    labels = labels.long()
    valid = labels != IGNORE_LABEL
    count = int(valid.sum())
    if count == 0:
        return logits.sum() * 0.0, 0
    num_classes = logits.shape[1]
    every = count == labels.shape[0]  # no row to drop: skip the copies of the selection (same values)
    chosen = labels if every else labels[valid]
    if int(chosen.min()) < 0 or int(chosen.max()) >= num_classes:
        raise ValueError(f"labels must be in 0..{num_classes - 1} or IGNORE_LABEL, got range "
                         f"{int(chosen.min())}..{int(chosen.max())}")
    log_probs = torch.log_softmax(logits if every else logits[valid], dim=1)
    nll = -log_probs.gather(1, chosen[:, None])[:, 0]
    if class_weights is not None:
        nll = nll * class_weights.to(nll.dtype)[chosen]
    if row_weights is not None:
        nll = nll * (row_weights if every else row_weights[valid]).to(nll.dtype)
    return nll.mean(), count


def opacity_row_weights(
    opacity_logits: torch.Tensor,  # [N] logits of the Gaussians' opacities
    counted: torch.Tensor,  # [N] bool: the rows a loss averages over
    power: float,
) -> torch.Tensor:  # [N] float32
    """Per-Gaussian weights ``opacity ** power`` scaled to mean 1 over the ``counted`` rows (``LossConfig.
    opacity_power``), computed in float64: Gaussians that share one opacity get exactly 1.0 each. Without a counted
    row, or with ``power == 0``, every weight is 1."""
    if power < 0:
        raise ValueError(f"opacity_power must be >= 0, got {power}")
    if power == 0 or not bool(counted.any()):
        return torch.ones(opacity_logits.shape[0], dtype=torch.float32, device=opacity_logits.device)
    weights = torch.sigmoid(opacity_logits.double()) ** power
    scale = weights[counted].mean()
    if not bool(scale > 0):  # every counted Gaussian at opacity 0 (a logit of -inf): nothing to prefer
        return torch.ones(opacity_logits.shape[0], dtype=torch.float32, device=opacity_logits.device)
    return (weights / scale).float()


def partial_label_nll(
    logits: torch.Tensor,  # [P, C]
    candidates: torch.Tensor,  # [U] int64 column indices
) -> torch.Tensor:  # [P]
    """``-log sum_{c in candidates} softmax(logits)_c`` per row: the cross-entropy of a row known only to belong
    to *one of* the candidate classes (partial-label learning). Stable for any finite logits."""
    return torch.logsumexp(logits, dim=1) - torch.logsumexp(logits[:, candidates], dim=1)


def text_cross_entropy(
    logits: torch.Tensor,  # [P, C]
    labels: torch.Tensor,  # [P] int, class index in 0..C-1 or IGNORE_LABEL
    class_weights: torch.Tensor | None = None,  # [C]
    unlabelled_columns: torch.Tensor | None = None,  # [U] int64 columns an IGNORE row may belong to
    unlabelled_weight: float = 1.0,
    row_weights: torch.Tensor | None = None,  # [P] weight of each row's term; None: all 1
) -> tuple[torch.Tensor, int]:
    """Text cross-entropy of labelled rows, plus (``unlabelled_columns`` given) the partial-label term of the
    IGNORE rows weighted by ``unlabelled_weight``: ``(sum of the terms / rows counted, rows counted)``. With
    ``row_weights`` every row's term, labelled or not, is multiplied by its weight.

    Without ``unlabelled_columns`` this is :func:`masked_cross_entropy` (the same operations, bitwise)."""
    mean, count = masked_cross_entropy(logits, labels, class_weights, row_weights)
    if unlabelled_columns is None:
        return mean, count
    unlabelled = labels.long() == IGNORE_LABEL
    extra = int(unlabelled.sum())
    if extra == 0:
        return mean, count
    partial = partial_label_nll(logits[unlabelled], unlabelled_columns.to(logits.device))
    if row_weights is not None:
        partial = partial * row_weights[unlabelled].to(partial.dtype)
    partial = partial.sum()
    return (mean * count + unlabelled_weight * partial) / (count + extra), count + extra


def lovasz_jaccard_gradient(
    foreground_sorted: torch.Tensor,  # [C, P] float, 1 where the row belongs to the class, rows by decreasing error
) -> torch.Tensor:  # [C, P]
    """Increments ``J(first i rows) - J(first i - 1 rows)`` of the Jaccard loss ``J(M) = |M| / |F u M|`` of each
    class when the first ``i`` rows (by decreasing error) are the mispredicted set ``M``; ``F`` is the class's
    foreground. The Lovasz extension of ``J`` at errors ``e`` is ``sum_i e_(i) * increment_i``."""
    total = foreground_sorted.sum(dim=1, keepdim=True)  # |F|
    missed = foreground_sorted.cumsum(dim=1)  # |M n F| of each prefix
    taken = (1.0 - foreground_sorted).cumsum(dim=1)  # |M \ F| of each prefix
    jaccard = 1.0 - (total - missed) / (total + taken)  # |M| / |F u M|; the denominator is >= 1 after row 0
    return torch.cat([jaccard[:, :1], jaccard[:, 1:] - jaccard[:, :-1]], dim=1)


def lovasz_softmax(
    logits: torch.Tensor,  # [P, C]
    labels: torch.Tensor,  # [P] int, class index in 0..C-1 or IGNORE_LABEL
) -> torch.Tensor:  # scalar
    """Lovasz-softmax loss of the labelled rows: the mean, over the classes present among them, of the Lovasz
    extension of the class's Jaccard loss at the errors ``|[label == c] - softmax(logits)_c|``. Exact 0 (attached
    to the graph) without a labelled row. For one-hot probabilities it equals the mean of ``1 - IoU``."""
    labels = labels.long()
    valid = labels != IGNORE_LABEL
    if not bool(valid.any()):
        return logits.sum() * 0.0
    chosen = labels[valid]
    num_classes = logits.shape[1]
    if int(chosen.min()) < 0 or int(chosen.max()) >= num_classes:
        raise ValueError(f"labels must be in 0..{num_classes - 1} or IGNORE_LABEL, got range "
                         f"{int(chosen.min())}..{int(chosen.max())}")
    probs = torch.softmax(logits[valid], dim=1)  # [R, C]
    present = torch.unique(chosen)  # [K]
    foreground = (chosen[None, :] == present[:, None]).to(probs.dtype)  # [K, R]
    errors = (foreground - probs.T[present]).abs()  # [K, R]
    errors_sorted, order = torch.sort(errors, dim=1, descending=True)
    increments = lovasz_jaccard_gradient(foreground.gather(1, order))
    return (errors_sorted * increments).sum(dim=1).mean()


def masked_cosine_loss(
    predicted: torch.Tensor,  # [P, D] psi(M)
    target: torch.Tensor,  # [P, D] teacher features
    valid: torch.Tensor,  # [P] bool
) -> tuple[torch.Tensor, int]:
    """Mean of ``1 - cos(predicted, target)`` over valid rows, and their count."""
    count = int(valid.sum())
    if count == 0:
        return predicted.sum() * 0.0, 0
    cos = (normalize_rows(predicted[valid]) * normalize_rows(target[valid])).sum(-1)
    return (1.0 - cos).mean(), count


def combine_losses(
    text_3d: tuple[torch.Tensor, int],
    text_2d: tuple[torch.Tensor, int],
    cosine: tuple[torch.Tensor, int] | None,
    *,
    no_3dt_align: bool,
    no_vs_align: bool,
    cosine_weight: float = 1.0,
) -> LossTerms:
    """``L = L_3d + L_2d + w * L_cos`` with the ablation switches applied."""
    zero = text_2d[0] * 0.0
    t3, c3 = (zero, 0) if no_3dt_align else text_3d
    cs, cc = (zero, 0) if (no_vs_align or cosine is None) else cosine
    total = t3 + text_2d[0] + cosine_weight * cs
    return LossTerms(total, t3, text_2d[0], cs, c3, text_2d[1], cc)


# --- slow references (tests compare against these) -------------------------------------------


def reference_cross_entropy(logits: list[list[float]], labels: list[int]) -> float:
    """Mean cross-entropy in float64 Python, row by row (log-sum-exp with the max subtracted)."""
    terms = []
    for row, label in zip(logits, labels):
        if label == IGNORE_LABEL:
            continue
        top = max(row)
        log_z = top + math.log(sum(math.exp(x - top) for x in row))
        terms.append(log_z - row[label])
    return sum(terms) / len(terms) if terms else 0.0


def reference_text_cross_entropy(logits: list[list[float]], labels: list[int], weights: list[float] | None = None,
                                 unlabelled_columns: list[int] | None = None,
                                 unlabelled_weight: float = 1.0, row_weights: list[float] | None = None) -> float:
    """:func:`text_cross_entropy` in float64 Python, row by row: ``-r_i w_c log p_label`` for labelled rows,
    ``-r_i w_u log (sum of p over unlabelled_columns)`` for IGNORE rows when columns are given (``r_i``: the row's
    weight, 1 without ``row_weights``)."""
    terms = []
    for i, (row, label) in enumerate(zip(logits, labels)):
        total = sum(math.exp(x) for x in row)
        r = 1.0 if row_weights is None else row_weights[i]
        if label != IGNORE_LABEL:
            terms.append(-r * (1.0 if weights is None else weights[label]) * math.log(math.exp(row[label]) / total))
        elif unlabelled_columns is not None:
            terms.append(-r * unlabelled_weight * math.log(sum(math.exp(row[c]) for c in unlabelled_columns) / total))
    return sum(terms) / len(terms) if terms else 0.0


def reference_lovasz_softmax(logits: list[list[float]], labels: list[int]) -> float:
    """:func:`lovasz_softmax` in float64 Python from the definitions: per present class, the Lovasz extension
    ``sum_i m_(i) (J({first i}) - J({first i - 1}))`` with the Jaccard loss ``J(M) = |M| / |F u M|`` evaluated on
    Python sets of row indices (ties in the errors keep row order, as a stable descending sort)."""
    rows = [(row, label) for row, label in zip(logits, labels) if label != IGNORE_LABEL]
    if not rows:
        return 0.0
    probs = []
    for row, _ in rows:
        top = max(row)
        exps = [math.exp(x - top) for x in row]
        probs.append([e / sum(exps) for e in exps])
    losses = []
    for c in sorted({label for _, label in rows}):
        foreground = {i for i, (_, label) in enumerate(rows) if label == c}
        errors = [abs((1.0 if i in foreground else 0.0) - probs[i][c]) for i in range(len(rows))]
        order = sorted(range(len(rows)), key=lambda i: -errors[i])

        def jaccard(mispredicted: set) -> float:
            union = foreground | mispredicted
            return len(mispredicted) / len(union) if union else 0.0

        total, previous = 0.0, 0.0
        for i in range(len(order)):
            current = jaccard(set(order[:i + 1]))
            total += errors[order[i]] * (current - previous)
            previous = current
        losses.append(total)
    return sum(losses) / len(losses)


def reference_cosine_loss(predicted: list[list[float]], target: list[list[float]], valid: list[bool]) -> float:
    """Mean ``1 - cos`` in float64 Python over the valid rows."""
    terms = []
    for p, t, ok in zip(predicted, target, valid):
        if not ok:
            continue
        dot = sum(a * b for a, b in zip(p, t))
        norm_p = max(math.sqrt(sum(a * a for a in p)), COSINE_NORM_EPS)
        norm_t = max(math.sqrt(sum(b * b for b in t)), COSINE_NORM_EPS)
        terms.append(1.0 - dot / (norm_p * norm_t))
    return sum(terms) / len(terms) if terms else 0.0
