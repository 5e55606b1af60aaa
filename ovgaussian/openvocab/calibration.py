"""Calibrated stacking (generalized zero-shot learning): subtract gamma from the seen classes' scores before
the argmax, with gamma chosen by a protocol that never reads a label of an unseen class.

A classifier trained on seen classes only scores them higher than any unseen class; subtracting a constant
gamma from every seen score lets unseen classes win where their score is close (Chao et al., ECCV 2016).
Tuning gamma on the unseen labels is not legal. The protocol here:

1. a *calibration run*: a training with some seen classes held out as pseudo-unseen
   (``ovgaussian train --holdout-classes``; they are not supervised, exactly as the unseen classes are not);
2. the calibration run scores the Gaussians of the **train** split against the training classes only (the
   benchmark vocabulary minus the unseen classes): through that vocabulary's lookup every unseen-class label
   is IGNORE, so none is read (a test removes them and gets the same gamma);
3. for each candidate gamma, gamma is subtracted from the scores of the non-held-out classes; gamma is the one
   with the best harmonic mean of the mIoU over those classes and over the pseudo-unseen classes;
4. the benchmark scores the main run with gamma subtracted from every seen class (``StackedPredictor``).

Each step's choice (candidates, curve, held-out classes, scenes) is returned in ``Calibration`` and written
into the bench report.
"""

from __future__ import annotations

from typing import Iterable, NamedTuple, Sequence

import numpy as np

from ovgaussian.metrics import confusion_matrix, per_class_iou
from ovgaussian.text.vocabulary import Vocabulary, map_labels
from seggaussian.core.constants import IGNORE_LABEL, UNSEEN_CLASSES, read_class_names
from seggaussian.util.seeds import scene_seed

#: Candidate offsets: the scores are cosines in [-1, 1], the seen-unseen margin a fraction of that.
GAMMA_CANDIDATES = tuple(round(0.01 * i, 2) for i in range(0, 61))
#: Gaussians per calibration scene scored at most (seeded subsample: bounds memory on large scenes).
MAX_GAUSSIANS_PER_SCENE = 20_000


class Calibration(NamedTuple):
    """The chosen gamma and how it was chosen (JSON-ready through ``as_dict``).

    Fields:
        gamma: offset subtracted from the seen classes' scores.
        harmonic_mean: harmonic mean of the two mIoUs at gamma.
        seen_miou, pseudo_unseen_miou: mIoU over the non-held-out classes and over the held-out ones, at gamma.
        pseudo_unseen: names of the held-out seen classes.
        classes: names of the calibration vocabulary (the training classes; no unseen class).
        candidates: ``[G]`` gammas tried; curve: ``[G]`` harmonic means.
        num_scenes, num_gaussians: what was scored.
    """

    gamma: float
    harmonic_mean: float
    seen_miou: float
    pseudo_unseen_miou: float
    pseudo_unseen: tuple[str, ...]
    classes: tuple[str, ...]
    candidates: tuple[float, ...]
    curve: tuple[float, ...]
    num_scenes: int
    num_gaussians: int

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self._asdict().items()}


def stack_scores(scores: np.ndarray, seen: np.ndarray, gamma: float) -> np.ndarray:
    """``[M, K]`` scores with ``gamma`` subtracted from the columns where ``seen`` ``[K]`` is True."""
    return np.asarray(scores) - np.float32(gamma) * np.asarray(seen, dtype=np.float32)


def _mean_iou(iou: np.ndarray, classes: np.ndarray) -> float:
    values = iou[classes]
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else 0.0


def choose_gamma(scores: np.ndarray, labels: np.ndarray, pseudo_unseen: np.ndarray,
                 candidates: Sequence[float] = GAMMA_CANDIDATES) -> tuple[float, float, float, float, np.ndarray]:
    """Gamma maximizing the harmonic mean of the mIoUs of the non-held-out and the held-out classes.

    ``scores`` ``[M, C]`` of the calibration run against its C classes; ``labels`` ``[M]`` indices into them or
    IGNORE_LABEL; ``pseudo_unseen`` ``[P]`` the held-out indices. Ties go to the smallest gamma.
    Returns (gamma, harmonic mean, seen mIoU, pseudo-unseen mIoU, curve ``[G]``).
    """
    scores = np.asarray(scores, dtype=np.float32)
    labels = np.asarray(labels, dtype=np.int64)
    num = scores.shape[1]
    held = np.zeros(num, bool)
    held[np.asarray(pseudo_unseen, dtype=np.int64)] = True
    if not held.any() or held.all():
        raise ValueError("calibration: need at least one held-out and one other class")
    kept, held_ids = np.flatnonzero(~held), np.flatnonzero(held)
    best, curve = None, []
    for gamma in candidates:
        predicted = np.argmax(stack_scores(scores, ~held, gamma), axis=1)
        iou = per_class_iou(confusion_matrix(predicted, labels, num))
        seen_miou, unseen_miou = _mean_iou(iou, kept), _mean_iou(iou, held_ids)
        h = 0.0 if seen_miou + unseen_miou == 0 else 2 * seen_miou * unseen_miou / (seen_miou + unseen_miou)
        curve.append(h)
        if best is None or h > best[1]:
            best = (float(gamma), h, seen_miou, unseen_miou)
    return (*best, np.asarray(curve))


def calibration_samples(predictor, scenes: Iterable, vocabulary: Vocabulary, seed: int = 0):
    """(scores ``[M, C]``, labels ``[M]``, scene count) of the calibration scenes' Gaussians against ``vocabulary``.

    Labels go through ``vocabulary``'s lookup: a class outside it (every unseen class) is IGNORE and dropped
    before anything else looks at it.
    """
    all_scores, all_labels, count = [], [], 0
    for scene in scenes:
        labels = map_labels(scene.gaussians.extras["semantic"], vocabulary)
        keep = np.flatnonzero(labels != IGNORE_LABEL)
        if keep.size > MAX_GAUSSIANS_PER_SCENE:
            rng = np.random.default_rng(scene_seed(seed, scene.scene_id))
            keep = np.sort(rng.choice(keep, MAX_GAUSSIANS_PER_SCENE, replace=False))
        count += 1
        if keep.size == 0:
            continue
        vectors = predictor.encode(scene)[keep]
        all_scores.append(np.asarray(predictor.classify(vectors, vocabulary.class_ids), dtype=np.float32))
        all_labels.append(labels[keep])
    if not all_scores:
        raise ValueError("calibration: no labelled Gaussian of a training class in the calibration scenes")
    return np.concatenate(all_scores), np.concatenate(all_labels), count


def calibrate(predictor, scenes: Iterable, vocabulary: Vocabulary, pseudo_unseen: Sequence[str],
              candidates: Sequence[float] = GAMMA_CANDIDATES) -> Calibration:
    """Gamma of the calibration run ``predictor`` on ``scenes`` (train split) against ``vocabulary`` (training
    classes: no unseen class may be in it) with the held-out ``pseudo_unseen`` names."""
    bad = [n for n in vocabulary.names if n in UNSEEN_CLASSES]
    if bad:
        raise ValueError(f"calibration vocabulary holds unseen classes {bad}: their labels must not be read")
    missing = [n for n in pseudo_unseen if n not in vocabulary.names]
    if missing or not pseudo_unseen:
        raise ValueError(f"calibration: held-out classes {missing or '(none)'} are not training classes "
                         f"(train the calibration run with --holdout-classes)")
    scores, labels, num_scenes = calibration_samples(predictor, scenes, vocabulary)
    held = np.array([vocabulary.names.index(n) for n in pseudo_unseen], dtype=np.int64)
    gamma, h, seen_miou, unseen_miou, curve = choose_gamma(scores, labels, held, candidates)
    return Calibration(gamma, h, seen_miou, unseen_miou, tuple(pseudo_unseen), tuple(vocabulary.names),
                       tuple(float(c) for c in candidates), tuple(float(c) for c in curve), num_scenes,
                       int(labels.size))


class StackedPredictor:
    """A predictor whose seen classes' scores are lowered by ``gamma`` (the unseen classes are UNSEEN_CLASSES)."""

    def __init__(self, inner, gamma: float) -> None:
        self.inner = inner
        self.gamma = float(gamma)
        self.name = f"{getattr(inner, 'name', 'model')}+stacking"
        self._names = read_class_names()

    def encode(self, scene) -> np.ndarray:
        return self.inner.encode(scene)

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        seen = np.array([self._names[int(i)] not in UNSEEN_CLASSES for i in class_ids])
        return stack_scores(self.inner.classify(vectors, class_ids), seen, self.gamma)
