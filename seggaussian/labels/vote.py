"""A second label-transfer rule, compared with the shipped nearest-point rule by the transfer sweep: majority
vote of the ``k`` nearest candidates within the distance gate, with a brute-force reference.

Same candidates, kNN backend, spacing estimate and gate as ``seggaussian.labels.transfer.transfer_labels``; with
``k = 1`` its labels equal that function's labels.
"""

from __future__ import annotations

import numpy as np

from seggaussian.labels.config import TransferConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.knn import nearest_neighbours
from seggaussian.labels.transfer import distance_gate, median_spacing, prepare_inputs


def transfer_labels_vote(
    gaussian_means: np.ndarray,  # [N, 3]
    points: np.ndarray,  # [P, 3]
    semantic: np.ndarray,  # [P]
    k: int,
    config: TransferConfig | None = None,
) -> tuple[np.ndarray, float]:  # ([N] int32 labels, gate)
    """Majority vote of the ``k`` nearest candidates within the distance gate (ties: the label of the
    nearest voter). Same candidates (with ``candidates="all"`` unlabelled points vote for ignore), kNN
    backend, spacing estimate and gate as ``transfer_labels``; with ``k = 1`` the labels equal its labels."""
    config = config or TransferConfig()
    no_instance = np.zeros(len(np.asarray(semantic)), np.int32)
    prep = prepare_inputs(gaussian_means, points, semantic, no_instance, None, config)
    cand_points, cand_semantic = prep.points[prep.candidate_index], prep.semantic[prep.candidate_index]
    labels = np.full(len(prep.means), IGNORE_LABEL, np.int32)
    if not len(cand_points) or not len(prep.means):
        return labels, float(config.max_distance or config.gate_min)
    query = nearest_neighbours(cand_points, config.backend)
    gate = distance_gate(median_spacing(query, cand_points, config), config)
    finite = np.flatnonzero(np.isfinite(prep.means).all(axis=1))
    d, i = query(prep.means[finite], int(min(k, len(cand_points))))  # [Q, k], ascending distance
    labels[finite] = vote(cand_semantic[i], d <= gate)
    return labels, gate


def vote(labels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``[Q]`` majority label of each row of ``labels`` ``[Q, k]`` over its ``valid`` slots (slots ordered
    nearest first; ties go to the earliest slot; IGNORE_LABEL votes like any label); IGNORE_LABEL for rows
    without a valid slot."""
    counts = np.zeros(labels.shape, np.int64)
    for j in range(labels.shape[1]):
        counts += valid[:, j : j + 1] & (labels == labels[:, j : j + 1])
    counts = np.where(valid, counts, -1)
    best = np.argmax(counts, axis=1)  # first maximum = nearest voter among the tied labels
    out = labels[np.arange(len(labels)), best].astype(np.int32)
    return np.where(valid.any(axis=1), out, IGNORE_LABEL).astype(np.int32)


def transfer_labels_vote_reference(means, points, semantic, k: int, gate: float, candidates: str = "all") -> np.ndarray:
    """Brute-force reference of ``transfer_labels_vote`` for a given gate (tiny inputs only)."""
    means, points = np.asarray(means, np.float64), np.asarray(points, np.float64)
    semantic = np.asarray(semantic).astype(np.int32)
    cand = np.ones(len(points), bool) if candidates == "all" else semantic != IGNORE_LABEL
    cand_points, cand_semantic = points[cand], semantic[cand]
    out = np.full(len(means), IGNORE_LABEL, np.int32)
    for r, x in enumerate(means):
        if not np.isfinite(x).all() or not len(cand_points):
            continue
        d = np.sqrt(((cand_points - x) ** 2).sum(axis=1))
        voters = [int(cand_semantic[j]) for j in np.argsort(d, kind="stable")[:k] if d[j] <= gate]
        if voters:
            top = max(voters.count(v) for v in voters)
            out[r] = next(v for v in voters if voters.count(v) == top)
    return out
