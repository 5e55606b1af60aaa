"""Compiled label-map kernels (numba): the per-pixel vote, and a walk that votes as it blends.

``slot_vote`` is the one copy of the vote of ``labelmaps.py`` (the label whose contributors carry the most weight,
IGNORE_LABEL a label of its own, ties to the front-most slot) over one pixel's valid slots. Two kernels use it:

- ``vote_kernel``: label maps from stored blend weights (``compute_blend_weights``), with the soft per-class sums.
- ``walk_vote_kernel``: the blend-weight walk of ``rasterize_numba`` (the same ``_blend_step``, the same order), its
  top_k slots kept per tile and voted at the tile's end, so no ``[H, W, top_k]`` ids and weights are written. A pixel
  stops once its top_k slots are filled and their weights sum to ``min_alpha`` or more: past that point the walk can
  change nothing the vote reads (the slots are full, and the pixel's total alpha, those weights plus the residual
  of the rest, is already at least ``min_alpha``, whatever non-negative residual follows). Below ``min_alpha`` the
  walk goes on and sums the residual in the same order as the stored walk, so the threshold sees the same float.
  The walk looks up each Gaussian's labels once, not once per pixel. The maps equal ``render_label_maps(compute_blend_weights(...))`` bit for bit
  (tests/seggaussian/render).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from seggaussian.render.rasterize_numba import (
    _DONE_CHECK_EVERY, _JIT, _TILE, _TILE_PIXELS, _TWO, _ZERO, _blend_step, _row_range, _tile_pixels,
)

#: Pixels per parallel work item of ``vote_kernel`` (each item allocates its work arrays once).
_VOTE_BLOCK = 512


@numba.njit(inline="always", cache=True, nogil=True)
def slot_vote(labels, weights, n, ignore, slot_label, slot_total, slot_of):
    """``(label, total)`` over one pixel's ``n`` valid slots (``labels``/``weights`` ``[>= n]``, in slot order, every
    weight > 0): the label of the first slot whose label's summed weight is largest, and that sum; ``(ignore, 0)``
    when ``n`` is 0. One pass sums each distinct label's weights in slot order, a second picks the winner (a label
    met again has the same total: never larger). ``slot_*`` are work arrays of the same length."""
    distinct = 0
    for j in range(n):
        label = labels[j]
        s = 0
        while s < distinct and slot_label[s] != label:
            s += 1
        if s == distinct:
            slot_label[s] = label
            slot_total[s] = np.float32(0.0)
            distinct += 1
        slot_of[j] = s
        slot_total[s] += weights[j]
    best_label = ignore
    best_total = np.float32(0.0)
    for k in range(n):
        s = slot_of[k]
        if slot_total[s] > best_total:
            best_total = slot_total[s]
            best_label = slot_label[s]
    return best_label, best_total


@numba.njit(inline="always", cache=True, nogil=True)
def _sum(weights, n):
    """``weights[:n]`` summed in slot order (float32): a pixel's captured alpha."""
    total = np.float32(0.0)
    for k in range(n):
        total += weights[k]
    return total


@numba.njit(inline="always", cache=True, nogil=True)
def _labels_of(sem, inst, w, n, total_alpha, min_alpha, ignore, slot_label, slot_total, slot_of):
    """``(semantic, instance)`` of a pixel with ``n`` valid slots under the label-map rule (ignore below
    ``min_alpha``, or where ignore or nothing wins)."""
    if not total_alpha >= min_alpha:  # NaN too
        return ignore, ignore
    s_label, s_total = slot_vote(sem, w, n, ignore, slot_label, slot_total, slot_of)
    i_label, i_total = slot_vote(inst, w, n, ignore, slot_label, slot_total, slot_of)
    return (s_label if s_total > 0 else ignore), (i_label if i_total > 0 else ignore)


@numba.njit(parallel=True, cache=True)
def vote_kernel(ids, weights, residual, semantic, instance, min_alpha, ignore, sem_out, inst_out, soft):
    """Label maps of stored blend weights: ``ids``/``weights`` ``[P, K]``, ``residual``/``sem_out``/``inst_out``
    ``[P]``, ``soft`` ``[P, C]`` zeros (filled with each class's summed weight). A slot votes where its id is >= 0 and
    its weight > 0 (a zero weight adds nothing to any sum)."""
    num_pixels, k_max = ids.shape
    for block in prange((num_pixels + _VOTE_BLOCK - 1) // _VOTE_BLOCK):
        sem = np.empty(k_max, np.int64)
        inst = np.empty(k_max, np.int64)
        w = np.empty(k_max, np.float32)
        slot_label = np.empty(k_max, np.int64)
        slot_total = np.empty(k_max, np.float32)
        slot_of = np.empty(k_max, np.int64)
        for p in range(block * _VOTE_BLOCK, min(num_pixels, (block + 1) * _VOTE_BLOCK)):
            n = 0
            total_alpha = np.float32(0.0)
            for k in range(k_max):
                total_alpha += weights[p, k]
                gid = ids[p, k]
                if gid >= 0 and weights[p, k] > 0:
                    sem[n], inst[n], w[n] = semantic[gid], instance[gid], weights[p, k]
                    n += 1
                    if semantic[gid] != ignore:
                        soft[p, semantic[gid]] += weights[p, k]
            sem_out[p], inst_out[p] = _labels_of(sem, inst, w, n, total_alpha + residual[p], min_alpha, ignore,
                                                 slot_label, slot_total, slot_of)


@numba.njit(parallel=True, **_JIT)
def walk_vote_kernel(means2d, conics, opacities, rows, offsets, gids, tiles_x, width, height, top_k, semantic,
                     instance, min_alpha, ignore, sem_out, inst_out):
    """The blend-weight walk of ``rasterize_numba._weights_kernel`` voting at each tile's end (module docstring);
    writes ``sem_out``/``inst_out`` ``[H, W]`` (every pixel of the image)."""
    num_tiles = offsets.shape[0] - 1
    for t in prange(num_tiles):
        px = np.empty(_TILE_PIXELS, np.float32)
        py = np.empty(_TILE_PIXELS, np.float32)
        x0, y0 = _tile_pixels(t, tiles_x, px, py)
        start, end = offsets[t], offsets[t + 1]
        tr = np.ones(_TILE_PIXELS, np.float32)
        active = np.ones(_TILE_PIXELS, np.float32)
        weight = np.zeros(_TILE_PIXELS, np.float32)
        count = np.zeros(_TILE_PIXELS, np.int64)
        sem = np.empty((_TILE_PIXELS, top_k), np.int64)
        inst = np.empty((_TILE_PIXELS, top_k), np.int64)
        weights = np.zeros((_TILE_PIXELS, top_k), np.float32)
        residual = np.zeros(_TILE_PIXELS, np.float32)
        for i in range(_TILE_PIXELS):  # pixels outside the image record nothing
            if x0 + i % _TILE >= width or y0 + i // _TILE >= height:
                active[i] = _ZERO
        for k in range(start, end):
            if (k - start) % _DONE_CHECK_EVERY == 0 and k > start:
                if active.sum() == _ZERO:
                    break
            g = gids[k]
            mx, my = means2d[g, 0], means2d[g, 1]
            ca, cb2, cc = conics[g, 0], _TWO * conics[g, 1], conics[g, 2]
            op = opacities[g]
            i0, i1 = _row_range(rows, g, y0)
            for i in range(i0, i1):
                weight[i], tr[i], stop = _blend_step(px[i] - mx, py[i] - my, ca, cb2, cc, op, tr[i], active[i])
                active[i] = active[i] - stop
            g_sem, g_inst = semantic[g], instance[g]
            for i in range(i0, i1):
                if weight[i] > _ZERO:
                    c = count[i]
                    if c < top_k:
                        sem[i, c], inst[i, c], weights[i, c] = g_sem, g_inst, weight[i]
                        count[i] = c + 1
                        if c + 1 == top_k and _sum(weights[i], top_k) >= min_alpha:
                            active[i] = _ZERO  # the vote can no longer change
                    else:
                        residual[i] += weight[i]
        slot_label = np.empty(top_k, np.int64)
        slot_total = np.empty(top_k, np.float32)
        slot_of = np.empty(top_k, np.int64)
        for i in range(_TILE_PIXELS):
            x = x0 + i % _TILE
            y = y0 + i // _TILE
            if x >= width or y >= height:
                continue
            n = count[i]
            total_alpha = _sum(weights[i], n) + residual[i]
            sem_out[y, x], inst_out[y, x] = _labels_of(sem[i], inst[i], weights[i], n, total_alpha, min_alpha,
                                                       ignore, slot_label, slot_total, slot_of)
