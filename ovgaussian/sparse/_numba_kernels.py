"""Numba kernels of the sparse conv: kernel-map merge join, row gather, row scatter-add (all serial)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def merge_pairs(keys: np.ndarray, deltas: np.ndarray):  # pragma: no cover - compiled
    """For each delta, rows ``(i, j)`` with ``keys[j] == keys[i] + delta``; keys strictly increasing.

    Returns ``rows_i [D, M]``, ``rows_j [D, M]`` (valid up to ``counts[d]``), ``counts [D]``.
    Both ``keys + delta`` and ``keys`` are sorted, so one forward walk over each finds all matches.
    """
    m = keys.shape[0]
    num_deltas = deltas.shape[0]
    rows_i = np.empty((num_deltas, m), np.int64)
    rows_j = np.empty((num_deltas, m), np.int64)
    counts = np.zeros(num_deltas, np.int64)
    for d in range(num_deltas):
        delta = deltas[d]
        j = 0
        c = 0
        for i in range(m):
            q = keys[i] + delta
            while j < m and keys[j] < q:
                j += 1
            if j == m:
                break
            if keys[j] == q:
                rows_i[d, c] = i
                rows_j[d, c] = j
                c += 1
        counts[d] = c
    return rows_i, rows_j, counts


@numba.njit(cache=True, nogil=True)
def gather_rows(x: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[p] = x[rows[p]]`` (a plain loop: about 3x faster than ``index_select`` for 32 columns)."""
    for p in range(rows.shape[0]):
        r = rows[p]
        for c in range(x.shape[1]):
            out[p, c] = x[r, c]


@numba.njit(cache=True, nogil=True)
def scatter_add_rows(out: np.ndarray, rows: np.ndarray, y: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[rows[p]] += y[p]`` in increasing ``p`` (serial: deterministic, no atomics)."""
    for p in range(rows.shape[0]):
        r = rows[p]
        for c in range(out.shape[1]):
            out[r, c] += y[p, c]
