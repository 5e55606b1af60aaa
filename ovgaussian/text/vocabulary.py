"""The one vocabulary type: K classes of the top-100 list, their unseen subset, and the label lookup.

Built on ``seggaussian.core.classes``' benchmark vocabulary (``data_specs/vocabularies.json``): the benchmark
scores the K-class vocabulary (``benchmark_vocabulary``), training supervises its seen classes only
(``training_vocabulary``: the same rule minus the unseen classes).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from seggaussian.core.classes import benchmark_vocabulary as benchmark_class_ids
from seggaussian.core.constants import IGNORE_LABEL, UNSEEN_CLASSES, read_class_names

__all__ = [
    "Vocabulary", "benchmark_class_ids", "benchmark_vocabulary", "make_vocabulary", "map_labels",
    "to_vocabulary_labels", "training_vocabulary",
]


class Vocabulary(NamedTuple):
    """K classes of the top-100 list.

    Fields:
        class_ids: ``[K]`` int64 top-100 ids; vocabulary index i <-> class_ids[i].
        names: the K class names (prompted for the text embeddings).
        unseen: ``[U]`` int64 vocabulary indices of the unseen classes among them (never supervised).
        lut: ``[L]`` int64 lookup top-100 id -> vocabulary index or IGNORE_LABEL (L = number of top-100 classes).
        num_classes: the benchmark K the classes were drawn from; None for a hand-picked list of ids.
    """

    class_ids: np.ndarray
    names: tuple[str, ...]
    unseen: np.ndarray
    lut: np.ndarray
    num_classes: int | None = None


def make_vocabulary(class_ids: Sequence[int], class_names: Sequence[str] | None = None,
                    num_classes: int | None = None) -> Vocabulary:
    """Vocabulary of the given top-100 ids (order kept); unseen = the UNSEEN_CLASSES among them."""
    names_all = tuple(class_names) if class_names is not None else read_class_names()
    ids = np.asarray(list(class_ids), dtype=np.int64)
    if ids.ndim != 1 or ids.size == 0:
        raise ValueError("vocabulary: need at least one class id")
    if ids.min() < 0 or ids.max() >= len(names_all):
        raise ValueError(f"vocabulary: class ids must lie in 0..{len(names_all) - 1}")
    if np.unique(ids).size != ids.size:
        raise ValueError("vocabulary: duplicate class ids")
    names = tuple(names_all[i] for i in ids)
    unseen = np.array([i for i, n in enumerate(names) if n in UNSEEN_CLASSES], dtype=np.int64)
    lut = np.full(len(names_all), IGNORE_LABEL, dtype=np.int64)
    lut[ids] = np.arange(ids.size)
    return Vocabulary(ids, names, unseen, lut, num_classes)


def benchmark_vocabulary(num_classes: int) -> Vocabulary:
    """The K-class benchmark vocabulary (4 unseen + first K-4 others of top-100), ascending ids."""
    return make_vocabulary(benchmark_class_ids(num_classes), num_classes=num_classes)


def training_vocabulary(num_classes: int, holdout: Sequence[str] = ()) -> Vocabulary:
    """The seen classes of the K-class benchmark vocabulary (the benchmark's minus the unseen), ascending ids,
    minus the ``holdout`` names (pseudo-unseen classes of a calibration run; each must be a seen class)."""
    names = read_class_names()
    seen = [i for i in benchmark_class_ids(num_classes) if names[i] not in UNSEEN_CLASSES]
    unknown = sorted(set(holdout) - {names[i] for i in seen})
    if unknown:
        raise ValueError(f"--holdout-classes: {unknown} are not seen classes of the K={num_classes} vocabulary")
    seen = [i for i in seen if names[i] not in holdout]
    return make_vocabulary(seen, names, num_classes)


def to_vocabulary_labels(labels: np.ndarray, vocabulary: Vocabulary, what: str = "labels") -> np.ndarray:
    """Top-100 ids (or IGNORE_LABEL) -> vocabulary indices; ids outside the vocabulary -> IGNORE_LABEL.

    Strict (ground truth of the benchmark): any other value is an error naming ``what``."""
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iu":
        raise TypeError(f"{what}: ground-truth labels must be integers, got {labels.dtype}")
    flat = labels.astype(np.int64)
    valid = (flat >= 0) & (flat < vocabulary.lut.size)
    bad = ~valid & (flat != IGNORE_LABEL)
    if bad.any():
        raise ValueError(f"{what}: {int(bad.sum())} labels are neither a top-100 id nor IGNORE_LABEL "
                         f"(first: {int(flat[bad][0])})")
    return np.where(valid, vocabulary.lut[np.where(valid, flat, 0)], IGNORE_LABEL)


def map_labels(labels: np.ndarray, vocabulary: Vocabulary) -> np.ndarray:
    """int labels (top-100 ids, IGNORE_LABEL, anything else) -> int64 vocabulary index or IGNORE_LABEL.

    Lenient (training targets): a value that is not a top-100 id is not supervised."""
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iu":
        raise TypeError(f"labels must be integers, got dtype {labels.dtype}")
    wide = labels.astype(np.int64)
    inside = (wide >= 0) & (wide < vocabulary.lut.size)
    out = np.full(wide.shape, IGNORE_LABEL, dtype=np.int64)
    out[inside] = vocabulary.lut[wide[inside]]
    return out
