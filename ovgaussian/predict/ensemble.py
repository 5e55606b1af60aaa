"""An ensemble of trained runs as one predictor: their class scores averaged.

Each member encodes a scene into its own semantic vectors; the ensemble's vector of a Gaussian is the members'
vectors side by side (``[N, S_1 + S_2 + ...]``), so rendering it for 2D renders each member's vectors (the blend is
linear per channel). ``classify`` (class ids, the bench) and ``score_names`` (free-text names, ``ovgaussian
predict``) score each member's columns with that member (phi, then cosine against its text embeddings) and average
the ``[M, K]`` scores. Runs trained with other seeds disagree most on a fitted splat's boundary Gaussians, where one
run's decision is close to chance (benchmarks/results/bench_suite.md, "Training seeds").
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np


class EnsemblePredictor:
    """The mean of the class scores of ``members`` (predictors with ``encode``/``classify``, and for ``predict``
    ``encode_gaussians``/``score_names``; see module docstring)."""

    name = "ensemble"

    def __init__(self, members: Sequence, widths: Sequence[int]) -> None:
        if len(members) < 1 or len(members) != len(widths):
            raise ValueError("ensemble: give one semantic width per member, and at least one member")
        if any(int(w) < 1 for w in widths):
            raise ValueError(f"ensemble: semantic widths must be positive, got {list(widths)}")
        self.members = tuple(members)
        self.bounds = np.concatenate([[0], np.cumsum([int(w) for w in widths])])

    @property
    def trained_names(self) -> frozenset:
        """Class names every member was trained on."""
        return frozenset.intersection(*(frozenset(getattr(m, "trained_names", ())) for m in self.members))

    @property
    def checkpoint(self):
        """The first member's checkpoint folder (the run given with ``--run``)."""
        return getattr(self.members[0], "checkpoint", None)

    def _join(self, encode: Callable) -> np.ndarray:
        parts = [np.asarray(encode(m), np.float32) for m in self.members]
        for part, start, end in zip(parts, self.bounds[:-1], self.bounds[1:]):
            if part.ndim != 2 or part.shape[1] != end - start:
                raise ValueError(f"ensemble: a member returned vectors of shape {part.shape}, expected width "
                                 f"{end - start}")
        return np.concatenate(parts, axis=1)

    def _mean(self, vectors: np.ndarray, score: Callable) -> np.ndarray:
        vectors = np.asarray(vectors)
        if vectors.ndim != 2 or vectors.shape[1] != self.bounds[-1]:
            raise ValueError(f"ensemble: vectors of shape {vectors.shape}, expected width {self.bounds[-1]}")
        total = None
        for member, start, end in zip(self.members, self.bounds[:-1], self.bounds[1:]):
            scores = np.asarray(score(member, vectors[:, start:end]), np.float64)
            total = scores if total is None else total + scores
        return (total / len(self.members)).astype(np.float32)

    def encode(self, scene) -> np.ndarray:
        return self._join(lambda member: member.encode(scene))

    def encode_gaussians(self, gaussians) -> np.ndarray:
        return self._join(lambda member: member.encode_gaussians(gaussians))

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        return self._mean(vectors, lambda member, part: member.classify(part, class_ids))

    def score_names(self, vectors: np.ndarray, names: Sequence[str]) -> np.ndarray:
        return self._mean(vectors, lambda member, part: member.score_names(part, names))
