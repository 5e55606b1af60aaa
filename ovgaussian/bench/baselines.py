"""Non-learned baselines scored by the same benchmark code, fitted on training-split statistics only.

- ``majority``: every Gaussian and pixel gets the most frequent training class among the vocabulary
  classes that occur in training (a per-class prior; unseen classes never occur, so never predicted).
- ``nearest-colour``: the mean view-independent colour (``0.5 + SH_C0 * f_dc``) of the training
  Gaussians of each class; a Gaussian (3D) or a rendered pixel colour (2D, ``W c`` divided by its
  accumulated alpha) gets the class whose mean colour is nearest. Classes without training Gaussians
  (the unseen classes) are never predicted.

Both only see Gaussians of the ``train`` split with a label (IGNORE excluded); the unseen classes are
not used even if the train split were to hold them (same rule as the trainer).

``GroundTruthPredictor`` is not a baseline but the upper bound: it reads each scene's own labels (the tests'
reference predictor, and ``benchmarks/nva_oracle.py``: what the 2D path loses against the stored label maps).
"""

from __future__ import annotations

from typing import Iterable, NamedTuple

import numpy as np

from seggaussian.core.constants import IGNORE_LABEL, UNSEEN_CLASSES, read_class_names

#: Floor of the accumulated alpha a rendered colour is divided by (protects 0-coverage pixels; such
#: pixels are below the benchmark's min_alpha and never classified anyway).
COLOUR_ALPHA_FLOOR = 1e-6


class ClassStatistics(NamedTuple):
    """Per-class statistics of the training Gaussians.

    Fields:
        counts: ``[L]`` int64 labelled Gaussians per top-100 class (L = number of top-100 classes).
        colour_sums: ``[L, 3]`` float64 sums of their DC colours.
    """

    counts: np.ndarray
    colour_sums: np.ndarray


def collect_class_statistics(scenes: Iterable, num_classes: int | None = None) -> ClassStatistics:
    """Counts and colour sums per class over the Gaussians of ``scenes`` (unseen classes dropped)."""
    names = read_class_names()
    num_classes = num_classes or len(names)
    unseen = [names.index(n) for n in UNSEEN_CLASSES if n in names]
    counts = np.zeros(num_classes, dtype=np.int64)
    sums = np.zeros((num_classes, 3), dtype=np.float64)
    for scene in scenes:
        semantic = scene.gaussians.extras.get("semantic")
        if semantic is None:
            raise ValueError(f"scene {scene.scene_id}: Gaussians have no 'semantic' labels")
        labels = np.asarray(semantic).astype(np.int64)
        keep = (labels != IGNORE_LABEL) & (labels >= 0) & (labels < num_classes)
        keep &= ~np.isin(labels, unseen)
        colours = scene.gaussians.dc_colors().astype(np.float64)
        counts += np.bincount(labels[keep], minlength=num_classes)
        for channel in range(3):
            sums[:, channel] += np.bincount(labels[keep], weights=colours[keep, channel], minlength=num_classes)
    return ClassStatistics(counts, sums)


class MajorityPredictor:
    """Predicts the most frequent training class of the vocabulary everywhere."""

    name = "majority"

    def __init__(self, stats: ClassStatistics) -> None:
        with np.errstate(divide="ignore"):
            self.log_prior = np.log(stats.counts.astype(np.float64))  # -inf: class never seen in training

    def encode(self, scene) -> np.ndarray:
        return np.zeros((len(scene.gaussians), 1), dtype=np.float32)

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        prior = self.log_prior[np.asarray(class_ids)]
        if not np.isfinite(prior).any():  # no vocabulary class seen in training: all equal, argmax = 0
            prior = np.zeros_like(prior)
        return np.broadcast_to(prior, (vectors.shape[0], prior.size))


class NearestColourPredictor:
    """Class of the nearest per-class mean training colour."""

    name = "nearest-colour"

    def __init__(self, stats: ClassStatistics) -> None:
        with np.errstate(invalid="ignore", divide="ignore"):
            self.means = stats.colour_sums / stats.counts[:, None]  # NaN rows: class never seen
        self.seen = stats.counts > 0

    def encode(self, scene) -> np.ndarray:
        colours = scene.gaussians.dc_colors().astype(np.float32)
        # a 4th channel of ones: after blending it holds the accumulated alpha, used to un-premultiply
        return np.concatenate([colours, np.ones((colours.shape[0], 1), np.float32)], axis=1)

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        class_ids = np.asarray(class_ids)
        vectors = np.asarray(vectors, dtype=np.float64)
        colours = vectors[:, :3] / np.maximum(vectors[:, 3:4], COLOUR_ALPHA_FLOOR)
        means = self.means[class_ids]  # [K, 3]
        d2 = ((colours[:, None, :] - np.nan_to_num(means)[None]) ** 2).sum(axis=-1)
        scores = -d2
        scores[:, ~self.seen[class_ids]] = -np.inf
        if not self.seen[class_ids].any():
            scores[:] = 0.0
        return scores


class GroundTruthPredictor:
    """The one-hot of each Gaussian's stored top-100 label as its vector (an IGNORE label: all zeros)."""

    name = "ground-truth oracle"

    def encode(self, scene) -> np.ndarray:
        labels = np.asarray(scene.gaussians.extras["semantic"]).astype(np.int64)  # [N]
        num_classes = len(read_class_names())
        known = labels != IGNORE_LABEL
        if known.any() and (labels[known].min() < 0 or labels[known].max() >= num_classes):
            raise ValueError(f"scene {scene.scene_id}: Gaussian labels outside the {num_classes} top-100 ids")
        vectors = np.zeros((labels.size, num_classes), np.float32)  # [N, 100]
        vectors[np.flatnonzero(known), labels[known]] = 1.0
        return vectors

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        return vectors[:, class_ids]  # [M, K]


def fit_majority(train_scenes: Iterable) -> MajorityPredictor:
    return MajorityPredictor(collect_class_statistics(train_scenes))


def fit_nearest_colour(train_scenes: Iterable) -> NearestColourPredictor:
    return NearestColourPredictor(collect_class_statistics(train_scenes))
