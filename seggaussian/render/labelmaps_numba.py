"""Compiled label-map kernels (numba): the per-pixel vote, and a walk that votes as it blends.

``slot_vote`` is the one copy of the vote of ``labelmaps.py`` (the label whose contributors carry the most weight,
IGNORE_LABEL a label of its own, ties to the front-most slot) over one pixel's valid slots. Two kernels use it:

- ``vote_kernel``: label maps from stored blend weights (``compute_blend_weights``), with the soft per-class sums.
- ``walk_vote_kernel``: the blend-weight walk of ``rasterize_numba`` (the same ``_blend_step``, the same order), its
  top_k slots kept per tile (each slot's Gaussian and weight) and voted at the tile's end, so no ``[H, W, top_k]`` ids
  and weights are written. A pixel stops walking once nothing behind can change its maps:

  - its top_k slots are full and their weights sum to ``min_alpha`` or more (the vote reads only the slots, and the
    pixel's total alpha, those weights plus the residual of the rest, is already at least ``min_alpha``, whatever
    non-negative residual follows); or
  - every slot so far holds the same semantic and the same instance label, and their weights sum to ``min_alpha`` or
    more and exceed the pixel's transmittance, the most that all the Gaussians behind can still add to any other
    label (with the margins ``_SETTLE_REL`` and ``_SETTLE_ABS``, which cover the float32 rounding of the walk): that
    label wins both votes whatever follows. The inside of a surface stops here, a few Gaussians deep; pixels on a
    boundary between labels take the first rule.

  Below ``min_alpha`` the walk goes on and sums the residual in the same order as the stored walk, so the threshold
  sees the same float. Only the rows of a tile that still hold an active pixel are blended. The walk reads its
  Gaussians' data in chunks of ``_DONE_CHECK_EVERY``, gathered into small buffers first
  (``rasterize_numba._gather_chunk``, as the rasterizer's forward walk does). The maps equal
  ``render_label_maps(compute_blend_weights(...))`` bit for bit (tests/seggaussian/render).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from seggaussian.render.rasterize_numba import (
    _DONE_CHECK_EVERY, _JIT, _TILE, _TILE_PIXELS, _ZERO, _blend_step, _gather_chunk, _row_range, _tile_start,
)

#: Pixels per parallel work item of ``vote_kernel`` (each item allocates its work arrays once).
_VOTE_BLOCK = 512
#: Margins of the walk's early stop on one label: its slots' sum must exceed ``transmittance * _SETTLE_REL +
#: _SETTLE_ABS``. The weights still to come sum to the transmittance up to the rounding of at most ``top_k`` float32
#: steps (relative error below 1e-5), and each label's sum rounds as often; 1e-4 and 1e-6 leave a wide berth.
_SETTLE_REL, _SETTLE_ABS = np.float32(1.0 + 1e-4), np.float32(1e-6)


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
def _active_rows(active):
    """``[lo, hi)`` (uint64): the tile's pixels from the first to the last row that holds an active pixel (empty when
    none does); the rows outside it have nothing left to blend."""
    lo, hi = _TILE, 0
    for r in range(_TILE):
        any_active = False
        for c in range(_TILE):
            if active[r * _TILE + c] != _ZERO:
                any_active = True
                break
        if any_active:
            lo = min(lo, r)
            hi = r + 1
    if hi == 0:
        lo = 0
    return np.uint64(lo * _TILE), np.uint64(hi * _TILE)


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
    uk = np.uint64(top_k)
    for t in prange(num_tiles):
        x0, y0, px, py, tr, active = _tile_start(t, tiles_x, width, height)
        start, end = offsets[t], offsets[t + 1]
        weight = np.zeros(_TILE_PIXELS, np.float32)
        count = np.zeros(_TILE_PIXELS, np.uint64)
        slot_gid = np.empty(_TILE_PIXELS * top_k, np.int64)  # pixel i's slots at [i * top_k, i * top_k + count[i])
        slot_weight = np.zeros(_TILE_PIXELS * top_k, np.float32)
        captured = np.zeros(_TILE_PIXELS, np.float32)  # the slots' weights summed in slot order
        residual = np.zeros(_TILE_PIXELS, np.float32)
        uniform = np.ones(_TILE_PIXELS, np.bool_)  # every slot so far holds the first slot's two labels
        lo, hi = _active_rows(active)
        chunk = np.empty((_DONE_CHECK_EVERY, 6), np.float32)  # mx, my, conic a, 2 b, c, opacity
        chunk_rows = np.empty((_DONE_CHECK_EVERY, 2), np.int32)
        chunk_labels = np.empty((_DONE_CHECK_EVERY, 2), np.int64)
        for c0 in range(start, end, _DONE_CHECK_EVERY):
            if c0 > start:
                lo, hi = _active_rows(active)
                if lo == hi:
                    break
            c1 = min(end, c0 + _DONE_CHECK_EVERY)
            _gather_chunk(gids, c0, c1, means2d, conics, opacities, rows, chunk, chunk_rows)
            for j in range(c1 - c0):
                g = gids[c0 + j]
                chunk_labels[j, 0], chunk_labels[j, 1] = semantic[g], instance[g]
            for j in range(c1 - c0):
                g = gids[c0 + j]
                mx, my, ca, cb2, cc, op = chunk[j, 0], chunk[j, 1], chunk[j, 2], chunk[j, 3], chunk[j, 4], chunk[j, 5]
                i0, i1 = _row_range(chunk_rows, j, y0)
                i0, i1 = max(i0, lo), min(i1, hi)  # rows with no active pixel blend nothing
                for i in range(i0, i1):
                    weight[i], tr[i], stop = _blend_step(px[i] - mx, py[i] - my, ca, cb2, cc, op, tr[i], active[i])
                    active[i] = active[i] - stop
                g_sem, g_inst = chunk_labels[j, 0], chunk_labels[j, 1]
                for i in range(i0, i1):
                    w = weight[i]
                    if w > _ZERO:
                        c = count[i]
                        if c < uk:
                            first = i * uk
                            slot_gid[first + c] = g
                            slot_weight[first + c] = w
                            count[i] = c + np.uint64(1)
                            captured[i] += w
                            if c > 0 and uniform[i]:
                                f = slot_gid[first]
                                uniform[i] = semantic[f] == g_sem and instance[f] == g_inst
                            if captured[i] >= min_alpha and (c + np.uint64(1) == uk or (
                                    uniform[i] and captured[i] > tr[i] * _SETTLE_REL + _SETTLE_ABS)):
                                active[i] = _ZERO  # nothing behind can change the maps (module docstring)
                        else:
                            residual[i] += w
        sem = np.empty(top_k, np.int64)
        inst = np.empty(top_k, np.int64)
        slot_label = np.empty(top_k, np.int64)
        slot_total = np.empty(top_k, np.float32)
        slot_of = np.empty(top_k, np.int64)
        for i in range(_TILE_PIXELS):
            x = x0 + i % _TILE
            y = y0 + i // _TILE
            if x >= width or y >= height:
                continue
            n = count[i]
            first = np.uint64(i) * uk
            for j in range(n):
                f = slot_gid[first + j]
                sem[j], inst[j] = semantic[f], instance[f]
            sem_out[y, x], inst_out[y, x] = _labels_of(sem, inst, slot_weight[first:first + n], n,
                                                       captured[i] + residual[i], min_alpha, ignore, slot_label,
                                                       slot_total, slot_of)
