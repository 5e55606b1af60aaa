"""Segmentation metrics from one confusion matrix: per-class IoU, mIoU, per-class accuracy, mAcc, unseen share.

Conventions (see ``data_specs/BENCHMARK.md``):

- Labels are indices ``0..K-1`` into a vocabulary of K classes; ``IGNORE_LABEL`` marks "no label".
- A ground-truth ``IGNORE_LABEL`` removes the sample (it is never scored).
- A predicted ``IGNORE_LABEL`` (e.g. an uncovered pixel) with a valid ground truth is a miss: it is
  counted in an extra "no prediction" column, so it adds a false negative to the ground-truth class
  and a false positive to no class.
- IoU = TP / (TP + FP + FN); a class with TP + FP + FN = 0 (absent from prediction and ground truth)
  has IoU NaN and is left out of the mean. Accuracy = TP / (TP + FN), NaN for a class absent from the
  ground truth. A mean over no scored class is ``None``, never NaN.

``confusion_matrix`` is the fast path (``np.bincount``); ``confusion_matrix_reference`` is the
obviously-correct loop kept for the tests. ``unseen_share`` splits an all-class mIoU (NVA) into what the unseen
classes decide: the same matrix with their pixels right, and the seen classes' mIoU without their pixels.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from seggaussian.core.constants import IGNORE_LABEL


class SegmentationScores(NamedTuple):
    """Scores of one confusion matrix.

    Fields:
        iou: ``[K]`` per-class IoU, NaN where the class is absent from prediction and ground truth.
        acc: ``[K]`` per-class accuracy (recall), NaN where the class is absent from the ground truth.
        miou: mean of the finite IoUs over the scored classes, or None when no class is scored.
        macc: mean of the finite accuracies over the scored classes, or None.
        scored_classes: ``[S]`` vocabulary indices the means were taken over (those with a finite IoU).
        num_samples: ground-truth samples counted (ignore excluded).
        num_unpredicted: counted samples whose prediction was IGNORE_LABEL (misses).
    """

    iou: np.ndarray
    acc: np.ndarray
    miou: float | None
    macc: float | None
    scored_classes: np.ndarray
    num_samples: int
    num_unpredicted: int


def _check_labels(labels: np.ndarray, num_classes: int, what: str) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iu":
        raise TypeError(f"{what} labels must be integers, got dtype {labels.dtype}")
    labels = labels.reshape(-1).astype(np.int64)
    bad = (labels != IGNORE_LABEL) & ((labels < 0) | (labels >= num_classes))
    if bad.any():
        raise ValueError(
            f"{what} labels: {int(bad.sum())} values outside 0..{num_classes - 1} and not IGNORE_LABEL "
            f"(first: {int(labels[bad][0])})"
        )
    return labels


def confusion_matrix(predicted: np.ndarray, target: np.ndarray, num_classes: int) -> np.ndarray:
    """``[K, K+1]`` int64 counts: row = ground-truth class, column = predicted class (column K = none).

    Args:
        predicted: integer labels in ``0..K-1`` or IGNORE_LABEL, any shape.
        target: integer labels of the same shape, ``0..K-1`` or IGNORE_LABEL (not counted).
        num_classes: K.
    """
    if num_classes <= 0:
        raise ValueError(f"num_classes must be positive, got {num_classes}")
    if np.shape(predicted) != np.shape(target):
        raise ValueError(f"predicted {np.shape(predicted)} and target {np.shape(target)} differ in shape")
    pred = _check_labels(predicted, num_classes, "predicted")
    gt = _check_labels(target, num_classes, "target")
    keep = gt != IGNORE_LABEL
    pred, gt = pred[keep], gt[keep]
    pred = np.where(pred == IGNORE_LABEL, num_classes, pred)
    flat = gt * (num_classes + 1) + pred
    counts = np.bincount(flat, minlength=num_classes * (num_classes + 1))
    return counts.reshape(num_classes, num_classes + 1).astype(np.int64)


def confusion_matrix_reference(predicted, target, num_classes: int) -> np.ndarray:
    """Slow loop version of :func:`confusion_matrix` (for tests)."""
    out = np.zeros((num_classes, num_classes + 1), dtype=np.int64)
    for p, t in zip(np.asarray(predicted).reshape(-1).tolist(), np.asarray(target).reshape(-1).tolist()):
        if t == IGNORE_LABEL:
            continue
        if not 0 <= t < num_classes:
            raise ValueError(f"target label {t} outside 0..{num_classes - 1}")
        if p == IGNORE_LABEL:
            p = num_classes
        elif not 0 <= p < num_classes:
            raise ValueError(f"predicted label {p} outside 0..{num_classes - 1}")
        out[t, p] += 1
    return out


class ConfusionMatrix:
    """Accumulates one ``[K, K+1]`` confusion matrix over many scenes / views (the only mutable state
    of this module, held by the caller)."""

    def __init__(self, num_classes: int) -> None:
        if num_classes <= 0:
            raise ValueError(f"num_classes must be positive, got {num_classes}")
        self.num_classes = int(num_classes)
        self.counts = np.zeros((self.num_classes, self.num_classes + 1), dtype=np.int64)

    def update(self, predicted: np.ndarray, target: np.ndarray) -> None:
        """Add the samples of one scene or view (see :func:`confusion_matrix`)."""
        self.counts += confusion_matrix(predicted, target, self.num_classes)

    def scores(self, classes: Sequence[int] | np.ndarray | None = None) -> SegmentationScores:
        """Scores averaged over ``classes`` (vocabulary indices; all K when None)."""
        return scores_from_confusion(self.counts, classes)


def per_class_iou(counts: np.ndarray) -> np.ndarray:
    """``[K]`` IoU = TP / (TP + FP + FN) from ``[K, K+1]`` counts; NaN where the denominator is 0."""
    counts = np.asarray(counts, dtype=np.int64)
    k = counts.shape[0]
    tp = np.diag(counts[:, :k]).astype(np.float64)
    fn = counts.sum(axis=1) - tp  # includes the "no prediction" column
    fp = counts[:, :k].sum(axis=0) - tp
    denom = tp + fp + fn
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(denom > 0, tp / np.where(denom > 0, denom, 1.0), np.nan)


def per_class_accuracy(counts: np.ndarray) -> np.ndarray:
    """``[K]`` accuracy = TP / (TP + FN) from ``[K, K+1]`` counts; NaN for a class absent from the ground truth."""
    counts = np.asarray(counts, dtype=np.int64)
    k = counts.shape[0]
    tp = np.diag(counts[:, :k]).astype(np.float64)
    total = counts.sum(axis=1).astype(np.float64)
    return np.where(total > 0, tp / np.where(total > 0, total, 1.0), np.nan)


def _finite_mean(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else None


def scores_from_confusion(counts: np.ndarray, classes: Sequence[int] | np.ndarray | None = None) -> SegmentationScores:
    """Per-class IoU / accuracy of ``counts`` ``[K, K+1]`` and their means over ``classes`` (default all)."""
    counts = np.asarray(counts, dtype=np.int64)
    k = counts.shape[0]
    if counts.ndim != 2 or counts.shape[1] != k + 1:
        raise ValueError(f"confusion counts must have shape [K, K+1], got {counts.shape}")
    iou, acc = per_class_iou(counts), per_class_accuracy(counts)
    selected = np.arange(k) if classes is None else np.unique(np.asarray(classes, dtype=np.int64))
    if selected.size and (selected.min() < 0 or selected.max() >= k):
        raise ValueError(f"classes to average must lie in 0..{k - 1}")
    scored = selected[np.isfinite(iou[selected])]
    return SegmentationScores(
        iou=iou, acc=acc, miou=_finite_mean(iou[selected]), macc=_finite_mean(acc[selected]),
        scored_classes=scored, num_samples=int(counts.sum()), num_unpredicted=int(counts[:, k].sum()),
    )


class UnseenShare(NamedTuple):
    """How much of an all-class mIoU (e.g. NVA) the unseen classes decide, from one ``[K, K+1]`` matrix.

    Fields:
        as_scored: mIoU over every class, as scored.
        unseen_right: mIoU over every class had every pixel of an unseen class been predicted right, every other
            prediction unchanged (what perfect open-vocabulary transfer would give this model).
        seen_only: mIoU over the seen classes with the unseen classes' pixels left out (the seen classes' own
            quality: no false positive from an unseen pixel).
    Each is None when no class is scored.
    """

    as_scored: float | None
    unseen_right: float | None
    seen_only: float | None


def unseen_share(counts: np.ndarray, unseen: Sequence[int] | np.ndarray) -> UnseenShare:
    """``UnseenShare`` of ``counts`` ``[K, K+1]`` for the vocabulary indices ``unseen``."""
    counts = np.asarray(counts, dtype=np.int64)
    k = counts.shape[0]
    if counts.ndim != 2 or counts.shape[1] != k + 1:
        raise ValueError(f"confusion counts must have shape [K, K+1], got {counts.shape}")
    unseen = np.unique(np.asarray(unseen, dtype=np.int64))
    if unseen.size and (unseen.min() < 0 or unseen.max() >= k):
        raise ValueError(f"unseen classes must lie in 0..{k - 1}")
    seen = np.setdiff1d(np.arange(k), unseen)
    right = counts.copy()
    right[unseen] = 0
    right[unseen, unseen] = counts[unseen].sum(axis=1)
    left_out = counts.copy()
    left_out[unseen] = 0
    return UnseenShare(
        as_scored=scores_from_confusion(counts).miou,
        unseen_right=scores_from_confusion(right).miou,
        seen_only=scores_from_confusion(left_out, seen).miou,
    )


def miou(predicted: np.ndarray, target: np.ndarray, num_classes: int, classes=None) -> float | None:
    """mIoU of one prediction (convenience): see :func:`scores_from_confusion`."""
    return scores_from_confusion(confusion_matrix(predicted, target, num_classes), classes).miou


def miou_reference(predicted, target, num_classes: int, classes=None) -> float | None:
    """Loop version of :func:`miou` computing IoU per class from the sample lists (for tests)."""
    pred = np.asarray(predicted).reshape(-1).tolist()
    gt = np.asarray(target).reshape(-1).tolist()
    ious = []
    for c in range(num_classes) if classes is None else sorted(set(int(c) for c in classes)):
        tp = fp = fn = 0
        for p, t in zip(pred, gt):
            if t == IGNORE_LABEL:
                continue
            if p == c and t == c:
                tp += 1
            elif p == c:
                fp += 1
            elif t == c:
                fn += 1
        if tp + fp + fn:
            ious.append(tp / (tp + fp + fn))
    return sum(ious) / len(ious) if ious else None


def format_class_table(scores: SegmentationScores, class_names: Sequence[str]) -> str:
    """Markdown table: class, IoU (%), accuracy (%), ground-truth samples; '-' where NaN."""

    def pct(x: float) -> str:
        return "-" if not np.isfinite(x) else f"{100.0 * x:.2f}"

    lines = ["| class | IoU | acc |", "|---|---:|---:|"]
    for i, name in enumerate(class_names):
        lines.append(f"| {name} | {pct(scores.iou[i])} | {pct(scores.acc[i])} |")
    return "\n".join(lines)
