"""An ensemble of trained runs as one predictor: their class scores averaged.

Each member encodes a scene into its own semantic vectors; the ensemble's vector of a Gaussian is the members'
vectors side by side (``[N, S_1 + S_2 + ...]``), so rendering it for 2D renders each member's vectors (the blend is
linear per channel). ``classify`` scores each member's columns with that member (phi, then cosine against its text
embeddings) and averages the ``[M, K]`` scores. Runs trained with other seeds disagree most on a fitted splat's
boundary Gaussians, where one run's decision is close to chance (BENCHMARKS.md, "Session 16").
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


class EnsemblePredictor:
    """The mean of the class scores of ``members`` (predictors with ``encode``/``classify``; see module docstring)."""

    name = "ensemble"

    def __init__(self, members: Sequence, widths: Sequence[int]) -> None:
        if len(members) < 1 or len(members) != len(widths):
            raise ValueError("ensemble: give one semantic width per member, and at least one member")
        if any(int(w) < 1 for w in widths):
            raise ValueError(f"ensemble: semantic widths must be positive, got {list(widths)}")
        self.members = tuple(members)
        self.bounds = np.concatenate([[0], np.cumsum([int(w) for w in widths])])

    def encode(self, scene) -> np.ndarray:
        parts = [np.asarray(m.encode(scene), np.float32) for m in self.members]
        for part, start, end in zip(parts, self.bounds[:-1], self.bounds[1:]):
            if part.ndim != 2 or part.shape[1] != end - start:
                raise ValueError(f"ensemble: a member returned vectors of shape {part.shape}, expected width "
                                 f"{end - start}")
        return np.concatenate(parts, axis=1)

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        vectors = np.asarray(vectors)
        if vectors.ndim != 2 or vectors.shape[1] != self.bounds[-1]:
            raise ValueError(f"ensemble: vectors of shape {vectors.shape}, expected width {self.bounds[-1]}")
        total = None
        for member, start, end in zip(self.members, self.bounds[:-1], self.bounds[1:]):
            scores = np.asarray(member.classify(vectors[:, start:end], class_ids), np.float64)
            total = scores if total is None else total + scores
        return (total / len(self.members)).astype(np.float32)
