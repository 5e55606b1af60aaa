"""Training losses of OVGaussian (paper eq. 3-5).

- Text alignment (3D-to-text on Gaussians, 2D-to-text on rendered pixels): cross-entropy of
  ``logits = cos(phi(x), e_m) / temperature`` over the seen classes' text embeddings ``e_m``,
  averaged over the elements whose label is not ``IGNORE_LABEL``.
- Transductive variant (``LossConfig.unlabelled_as_unseen``): the elements without a seen-class label take the
  partial-label term ``-log sum_u p_u`` over the unseen classes' columns (:func:`text_cross_entropy`).
- Visual-semantic alignment: ``1 - cos(psi(M), teacher)`` averaged over valid pixels.
- ``L = L_3d + L_2d + w * L_cosine``; ``no_3dt_align`` drops L_3d, ``no_vs_align`` drops L_cosine.

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
) -> tuple[torch.Tensor, int]:
    """Mean cross-entropy over labelled rows (log-softmax, stable for any finite logits) and their count.

    With ``class_weights`` each row's term is multiplied by its class's weight and the sum is still divided
    by the row count (weights normalized over the training data keep the loss on the same scale)."""
    labels = labels.long()
    valid = labels != IGNORE_LABEL
    count = int(valid.sum())
    if count == 0:
        return logits.sum() * 0.0, 0
    num_classes = logits.shape[1]
    chosen = labels[valid]
    if int(chosen.min()) < 0 or int(chosen.max()) >= num_classes:
        raise ValueError(f"labels must be in 0..{num_classes - 1} or IGNORE_LABEL, got range "
                         f"{int(chosen.min())}..{int(chosen.max())}")
    log_probs = torch.log_softmax(logits[valid], dim=1)
    nll = -log_probs.gather(1, chosen[:, None])[:, 0]
    if class_weights is not None:
        nll = nll * class_weights.to(nll.dtype)[chosen]
    return nll.mean(), count


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
) -> tuple[torch.Tensor, int]:
    """Text cross-entropy of labelled rows, plus (``unlabelled_columns`` given) the partial-label term of the
    IGNORE rows weighted by ``unlabelled_weight``: ``(sum of the terms / rows counted, rows counted)``.

    Without ``unlabelled_columns`` this is :func:`masked_cross_entropy` (the same operations, bitwise)."""
    mean, count = masked_cross_entropy(logits, labels, class_weights)
    if unlabelled_columns is None:
        return mean, count
    unlabelled = labels.long() == IGNORE_LABEL
    extra = int(unlabelled.sum())
    if extra == 0:
        return mean, count
    partial = partial_label_nll(logits[unlabelled], unlabelled_columns.to(logits.device)).sum()
    return (mean * count + unlabelled_weight * partial) / (count + extra), count + extra


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
                                 unlabelled_weight: float = 1.0) -> float:
    """:func:`text_cross_entropy` in float64 Python, row by row: ``-w_c log p_label`` for labelled rows,
    ``-w_u log (sum of p over unlabelled_columns)`` for IGNORE rows when columns are given."""
    terms = []
    for row, label in zip(logits, labels):
        total = sum(math.exp(x) for x in row)
        if label != IGNORE_LABEL:
            terms.append(-(1.0 if weights is None else weights[label]) * math.log(math.exp(row[label]) / total))
        elif unlabelled_columns is not None:
            terms.append(-unlabelled_weight * math.log(sum(math.exp(row[c]) for c in unlabelled_columns) / total))
    return sum(terms) / len(terms) if terms else 0.0


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
