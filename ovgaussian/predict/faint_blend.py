"""Faint Gaussians read part of their semantic vector from the opaque Gaussians around them.

A fitted splat leaves many nearly transparent Gaussians: on the benchmark profile's fits 13 % of the labelled
Gaussians have an opacity under 0.05, and the model labels them right about half as often as the opaque ones
(benchmarks/results/bench_suite.md, "Faint Gaussians"). Such a Gaussian shows little of what it covers, in its own colour and in the voxel
it is pooled into (pooling is weighted by opacity), so its own vector is weak evidence. Its label is better read
from the surface it floats against. With ``o`` the opacities and ``N_k(i)`` the ``k`` Gaussians nearest to ``i``
(``i`` among them)::

    a_i  = o_i ** SELF_EXPONENT
    s'_i = a_i s_i + (1 - a_i) * sum_{j in N_k(i)} w_j s_j / sum_{j in N_k(i)} w_j,    w_j = max(o_j, MIN_WEIGHT)

An opaque Gaussian keeps its vector (``o = 1``: unchanged; the oracle sample's 0.95: 97.5 % its own), a faint
one takes mostly its opaque neighbours'. The blend is linear in the vectors, so the 2D maps rendered from the
blended vectors and an ensemble's averaged scores stay consistent with the 3D labels. ``k`` counts the Gaussian
itself; ``k <= 1`` changes nothing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Exponent of a Gaussian's own opacity in the weight of its own vector (0.5: opacity 0.25 keeps half).
SELF_EXPONENT = 0.5
#: Floor of a neighbour's weight, so a neighbourhood of fully transparent Gaussians averages evenly, not 0/0.
MIN_WEIGHT = 1e-3


def _check(means: np.ndarray, opacity: np.ndarray, vectors: np.ndarray, neighbours: int) -> None:
    n = len(vectors)
    if means.shape != (n, 3) or opacity.shape != (n,) or vectors.ndim != 2:
        raise ValueError(f"faint blend: means [N, 3], opacity [N] and vectors [N, S] expected, got "
                         f"{means.shape}, {opacity.shape}, {vectors.shape}")
    if neighbours < 0:
        raise ValueError(f"faint blend: neighbours must be >= 0, got {neighbours}")
    if not (np.isfinite(means).all() and np.isfinite(opacity).all()):
        raise ValueError("faint blend: means or opacity hold NaN/Inf")


def faint_blend(means: np.ndarray,  # [N, 3] positions
                opacity: np.ndarray,  # [N] opacities in [0, 1]
                vectors: np.ndarray,  # [N, S] semantic vectors
                neighbours: int) -> np.ndarray:  # -> [N, S] float32
    """The vectors with each Gaussian's blended with its ``neighbours`` nearest (module docstring); a k-d tree
    query, then one weighted gather per neighbour rank (no ``[N, k, S]`` array)."""
    means = np.asarray(means, np.float64)
    opacity = np.asarray(opacity, np.float64).reshape(-1)
    vectors = np.asarray(vectors, np.float32)
    _check(means, opacity, vectors, neighbours)
    k = min(int(neighbours), len(vectors))
    if k <= 1:
        return vectors.copy()
    _, index = cKDTree(means).query(means, k=k)  # [N, k], nearest first
    opacity = np.clip(opacity, 0.0, 1.0)
    weight = np.maximum(opacity, MIN_WEIGHT)
    total = np.zeros(vectors.shape, np.float64)
    norm = np.zeros(len(vectors), np.float64)
    for rank in range(k):
        w = weight[index[:, rank]]
        total += w[:, None] * vectors[index[:, rank]]
        norm += w
    own = opacity ** SELF_EXPONENT
    out = own[:, None] * vectors + (1.0 - own[:, None]) * (total / norm[:, None])
    return out.astype(np.float32)


def faint_blend_reference(means: np.ndarray, opacity: np.ndarray, vectors: np.ndarray,
                          neighbours: int) -> np.ndarray:
    """:func:`faint_blend` written plainly: every Gaussian's distances to all others, its ``k`` smallest (stable
    sort: ties go to the lower index), a loop over Gaussians. O(N^2): tests only."""
    means = np.asarray(means, np.float64)
    opacity = np.asarray(opacity, np.float64).reshape(-1)
    vectors = np.asarray(vectors, np.float32)
    _check(means, opacity, vectors, neighbours)
    k = min(int(neighbours), len(vectors))
    out = vectors.astype(np.float64).copy()
    if k <= 1:
        return out.astype(np.float32)
    for i in range(len(vectors)):
        distance = np.linalg.norm(means - means[i], axis=1)
        nearest = np.argsort(distance, kind="stable")[:k]
        weights = np.array([max(min(max(opacity[j], 0.0), 1.0), MIN_WEIGHT) for j in nearest])
        mean = sum(w * vectors[j].astype(np.float64) for w, j in zip(weights, nearest)) / weights.sum()
        own = min(max(opacity[i], 0.0), 1.0) ** SELF_EXPONENT
        out[i] = own * vectors[i] + (1.0 - own) * mean
    return out.astype(np.float32)
