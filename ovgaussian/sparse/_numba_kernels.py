"""Numba kernels of the sparse conv (kernel-map merge join, row gather / scatter-add, GEMM-plan building) and of the
trilinear devoxelization (corners, blend, its transpose); all serial."""

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


@numba.njit(cache=True, nogil=True)
def gather_neighbour_block(x: np.ndarray, neighbours: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out[i, p*C:(p+1)*C] = x[neighbours[i, p]]``, zeros where ``neighbours[i, p] >= len(x)`` (absent).

    ``out`` is ``[n, P * C]``: the im2col block of ``n`` output rows over ``P`` kernel offsets.
    """
    num_rows = x.shape[0]
    c_in = x.shape[1]
    for i in range(neighbours.shape[0]):
        for p in range(neighbours.shape[1]):
            r = neighbours[i, p]
            base = p * c_in
            if r < num_rows:
                for c in range(c_in):
                    out[i, base + c] = x[r, c]
            else:
                for c in range(c_in):
                    out[i, base + c] = 0.0


@numba.njit(cache=True, nogil=True)
def fill_neighbour_table(in_rows, out_rows, starts, num_in, num_out, word_bits):  # pragma: no cover - compiled
    """Neighbour table and pattern bit masks of a kernel map given as concatenated pairs.

    Pairs of offset ``k`` are ``in_rows[starts[k]:starts[k + 1]]`` / ``out_rows[...]``. Returns
    ``table [num_out, K]`` (``num_in`` where absent), ``words [num_out, W]`` (bit ``k % word_bits``
    of word ``k // word_bits`` set when offset ``k`` has an input) and the number of pairs that hit an
    already filled slot (two inputs for one (row, offset): not expressible as a table).
    When every offset's output rows are strictly increasing (all maps built here) the table is
    filled row by row, a K-way merge (cache friendly); otherwise offset by offset.
    """
    k_vol = starts.shape[0] - 1
    num_words = max(1, (k_vol + word_bits - 1) // word_bits)
    table = np.empty((num_out, k_vol), np.int64)
    words = np.zeros((num_out, num_words), np.int64)
    collisions = 0
    increasing = True
    for k in range(k_vol):
        for p in range(starts[k] + 1, starts[k + 1]):
            if out_rows[p] <= out_rows[p - 1]:
                increasing = False
    if increasing:
        ptr = starts[:-1].copy()
        for o in range(num_out):
            for k in range(k_vol):
                p = ptr[k]
                if p < starts[k + 1] and out_rows[p] == o:
                    table[o, k] = in_rows[p]
                    words[o, k // word_bits] |= np.int64(1) << (k % word_bits)
                    ptr[k] = p + 1
                else:
                    table[o, k] = num_in
        return table, words, collisions
    table[:, :] = num_in
    for k in range(k_vol):
        w = k // word_bits
        bit = np.int64(1) << (k % word_bits)
        for p in range(starts[k], starts[k + 1]):
            o = out_rows[p]
            if table[o, k] != num_in:
                collisions += 1
            table[o, k] = in_rows[p]
            words[o, w] |= bit
    return table, words, collisions


@numba.njit(cache=True, nogil=True)
def gather_table_block(table, rows, offsets):  # pragma: no cover - compiled
    """``table[rows][:, offsets]`` as a new contiguous ``[len(rows), len(offsets)]`` array."""
    out = np.empty((rows.shape[0], offsets.shape[0]), np.int64)
    for i in range(rows.shape[0]):
        r = rows[i]
        for p in range(offsets.shape[0]):
            out[i, p] = table[r, offsets[p]]
    return out


@numba.njit(cache=True, nogil=True)
def residual_pairs(table, group_of_row, group_bits, num_in):  # pragma: no cover - compiled
    """Pairs of a neighbour table outside each row's group pattern, per offset, rows increasing.

    ``table [M, K]``, ``group_of_row [M]`` (negative: no group), ``group_bits [G, K]`` (uint8, 1 where
    the group gathers the offset). Returns ``in_rows``, ``out_rows`` (concatenated offset by offset)
    and ``counts [K]``.
    """
    m, k_vol = table.shape
    counts = np.zeros(k_vol, np.int64)
    for r in range(m):
        g = group_of_row[r]
        for k in range(k_vol):
            if table[r, k] < num_in and (g < 0 or group_bits[g, k] == 0):
                counts[k] += 1
    starts = np.zeros(k_vol + 1, np.int64)
    for k in range(k_vol):
        starts[k + 1] = starts[k] + counts[k]
    in_rows = np.empty(starts[k_vol], np.int64)
    out_rows = np.empty(starts[k_vol], np.int64)
    fill = starts[:-1].copy()
    for r in range(m):
        g = group_of_row[r]
        for k in range(k_vol):
            j = table[r, k]
            if j < num_in and (g < 0 or group_bits[g, k] == 0):
                in_rows[fill[k]] = j
                out_rows[fill[k]] = r
                fill[k] += 1
    return in_rows, out_rows, counts


@numba.njit(cache=True, nogil=True)
def trilinear_corners(table, rows, offsets, out_rows, out_weights) -> None:  # pragma: no cover - compiled
    """Trilinear corners of points in their voxels (``ovgaussian.sparse.devoxelize.trilinear_gather``).

    Point ``i`` lies in voxel ``rows[i]`` at ``offsets[i]`` (voxel edges, centre 0.5). ``table`` is the ``[M, 27]``
    table of the voxels' neighbours (row or -1: ``devoxelize.neighbour_table``) at the offsets ``(dx, dy, dz)`` in
    ``{-1, 0, 1}^3``, column ``9 (dx + 1) + 3 (dy + 1) + dz + 1``. Corner ``k`` has bits
    ``(x, y, z) = (k >> 2 & 1, k >> 1 & 1, k & 1)``: 1 takes the neighbour on the point's side of the centre along
    that axis. A corner that is not occupied gets the own row and weight 0; the others the product of
    ``1 - |offset - 0.5|`` (own side) and ``|offset - 0.5|`` (neighbour), all normalized to sum 1 per point.
    """
    side = np.empty(3, np.int64)
    share = np.empty(3, np.float64)
    weights = np.empty(8, np.float64)
    for i in range(rows.shape[0]):
        own_row = rows[i]
        for a in range(3):
            centred = np.float64(offsets[i, a]) - 0.5
            side[a] = -1 if centred < 0 else 1
            share[a] = min(abs(centred), 0.5)
        total = 0.0
        for k in range(8):
            weight = 1.0
            column = 13  # (0, 0, 0)
            for a in range(3):
                if (k >> (2 - a)) & 1:
                    weight *= share[a]
                    column += side[a] * (9, 3, 1)[a]
                else:
                    weight *= 1.0 - share[a]
            row = table[own_row, column]
            if row < 0:
                row = own_row
                weight = 0.0
            out_rows[i, k] = row
            weights[k] = weight
            total += weight
        for k in range(8):
            out_weights[i, k] = weights[k] / total


@numba.njit(cache=True, nogil=True)
def blend_rows(x, rows, weights, out) -> None:  # pragma: no cover - compiled
    """``out[i] = sum_k weights[i, k] * x[rows[i, k]]``."""
    for i in range(rows.shape[0]):
        for c in range(x.shape[1]):
            out[i, c] = 0.0
        for k in range(rows.shape[1]):
            r = rows[i, k]
            w = weights[i, k]
            if w != 0.0:
                for c in range(x.shape[1]):
                    out[i, c] += w * x[r, c]


@numba.njit(cache=True, nogil=True)
def blend_scatter(out, rows, weights, y) -> None:  # pragma: no cover - compiled
    """``out[rows[i, k]] += weights[i, k] * y[i]`` in increasing ``(i, k)`` (serial: deterministic)."""
    for i in range(rows.shape[0]):
        for k in range(rows.shape[1]):
            r = rows[i, k]
            w = weights[i, k]
            if w != 0.0:
                for c in range(y.shape[1]):
                    out[r, c] += w * y[i, c]
