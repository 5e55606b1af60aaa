"""Compiled CPU blending kernels (numba), parallel over 16x16 tiles, float32.

Layout (see ../shared/notes/cpu-kernels.md beside the checkout): a tile's Gaussians are the outer loop, its 256 pixels
the branch-free inner loop (arithmetic 0/1 masks instead of selects, a polynomial exp), so LLVM
vectorizes the pixel loop. A tile stops as soon as every pixel has stopped.

The blending rule and the gradient convention at the ALPHA_MAX clamp are those of ``reference.py``
(gsplat's: no gradient to opacity / 2D Gaussian where alpha is clamped). The backward pass replays the
forward walk front to back; the colour sum behind a Gaussian is ``C_final - C_up_to_it``, so no division
by ``1 - alpha`` is needed except for the accumulated-alpha term (``1 - alpha >= 1 - ALPHA_MAX``).
Gradients are written to one slot per live (tile, Gaussian) intersection (one that some pixel of the tile reached
before stopping) by the thread owning the tile, then summed per Gaussian in tile order: deterministic for any
thread count.

Kernels run with fast-math flags (``FASTMATH``, without ``reassoc``, so a kernel gives the same bits whether
numba compiled it in this process or loaded it from its cache): inputs must be finite, which the projection
guarantees for the Gaussians it marks valid (only those are binned).

The kernels use numba's parallel threading layer: calling them in a forked child of a process that
already ran one (e.g. a DataLoader worker) can kill the child; use the ``spawn`` start method or no
worker processes. Every kernel is called through ``parallel.run_parallel``.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from seggaussian.core.constants import ALPHA_MAX, ALPHA_MIN, RADIUS_SIGMAS, TILE_SIZE, TRANSMITTANCE_MIN
from seggaussian.render.parallel import run_parallel
from seggaussian.render.results import BlendWeights, TileBins

_f32 = np.float32
# float32 constants: a bare Python float literal would promote the kernels' arithmetic to float64.
_ZERO, _ONE, _HALF, _TWO = _f32(0.0), _f32(1.0), _f32(0.5), _f32(2.0)
_ALPHA_MAX, _ALPHA_MIN, _T_MIN = _f32(ALPHA_MAX), _f32(ALPHA_MIN), _f32(TRANSMITTANCE_MIN)
_CUTOFF = _f32(RADIUS_SIGMAS**2)
_INV16 = _f32(1.0 / 16.0)
_C2, _C3, _C4, _C5, _C6 = _f32(1 / 2), _f32(1 / 3), _f32(1 / 4), _f32(1 / 5), _f32(1 / 6)
_TILE = TILE_SIZE
_UTILE = np.uint64(TILE_SIZE)
_U0, _U1, _U2 = np.uint64(0), np.uint64(1), np.uint64(2)
_TILE_PIXELS = TILE_SIZE * TILE_SIZE
#: Tiles check "every pixel stopped" once per this many Gaussians (a reduction over 256 pixels).
_DONE_CHECK_EVERY = 32

#: Fast-math flags of every kernel: all of LLVM's except ``reassoc``. With ``reassoc`` the optimizer may reorder
#: float sums, and numba optimizes a ``prange`` body once when it compiles it fresh and once more when it links
#: it into the caller's module, whose object code is what ``cache=True`` stores: a freshly compiled kernel and
#: the same kernel loaded from the cache then summed in different orders (different gradients, a different fit;
#: issue 16). Without ``reassoc`` the float arithmetic is the order written here, compiled or cached; the pixel
#: sums that needed ``reassoc`` to vectorize are written as explicit element-wise folds (``_range_sum``).
FASTMATH = frozenset({"nnan", "ninf", "nsz", "arcp", "contract", "afn"})
_JIT = dict(cache=True, fastmath=set(FASTMATH), nogil=True, error_model="numpy")


@numba.njit(inline="always", **_JIT)
def _exp_neg(x):
    """exp(x) for x in [-RADIUS_SIGMAS^2 / 2, 0]: (degree-6 Taylor of exp(x/16))^16, rel. error < 2e-6 (float32)."""
    y = x * _INV16
    p = _ONE + y * (_ONE + y * _C2 * (_ONE + y * _C3 * (_ONE + y * _C4 * (_ONE + y * _C5 * (_ONE + y * _C6)))))
    p = p * p
    p = p * p
    p = p * p
    return p * p


@numba.njit(inline="always", **_JIT)
def _fold(x, dst, src, count):
    """``x[dst:dst + count] += x[src:src + count]`` (non-overlapping ranges): an element-wise, vectorized add."""
    for q in range(count):
        x[dst + q] = x[dst + q] + x[src + q]


@numba.njit(inline="always", **_JIT)
def _range_sum(x, i0, i1):
    """Sum of ``x[i0:i1]`` (uint64 bounds, whole tile rows: both multiples of ``_TILE``), overwriting it, in a fixed
    order: the upper half of the rows is folded onto the lower half until one row is left, then that row's upper
    half onto its lower half down to one value. Each fold is an element-wise add, which LLVM vectorizes without
    reordering anything, and the order depends on the number of rows only: the same for any thread count."""
    rows = (i1 - i0) // _UTILE
    if rows == _U0:
        return _ZERO
    while rows > _U1:
        half = rows // _U2
        _fold(x, i0, i0 + (rows - half) * _UTILE, half * _UTILE)
        rows = rows - half
    width = _UTILE // _U2
    while width > _U0:
        _fold(x, i0, i0 + width, width)
        width = width // _U2
    return x[i0]


@numba.njit(inline="always", **_JIT)
def _row_range(rows, g, y0):
    """``[i0, i1)`` (uint64): the pixels (row-major in the tile whose top row is ``y0``) of the tile rows that Gaussian
    ``g``'s pixel box ``rows[g] = (v_min, v_max)`` covers. The box holds its 3-sigma ellipse with a margin for float32
    rounding, so every pixel outside the range fails the per-pixel cut-off: skipping it changes nothing. Unsigned, so
    that numba's indexing has no negative-index wrap-around to check and the pixel loops stay vectorized."""
    r0 = max(0, np.int64(rows[g, 0]) - y0)
    r1 = max(r0, min(_TILE - 1, np.int64(rows[g, 1]) - y0) + 1)
    return np.uint64(r0 * _TILE), np.uint64(r1 * _TILE)


@numba.njit(inline="always", **_JIT)
def _blend_step(dx, dy, ca, cb2, cc, op, tr, active):
    """One Gaussian at one pixel under the 3DGS blending rule (3-sigma cut, alpha clamp, alpha skip, early stop).

    ``(dx, dy)``: pixel centre minus the projected mean; ``(ca, cb2, cc)``: conic with the doubled off-diagonal;
    ``op``: opacity; ``tr``: transmittance before this Gaussian; ``active``: 1 while the pixel still blends.
    Returns ``(weight, tr_after, stop)``: the blend weight ``alpha * tr`` (0 when skipped), the transmittance after
    it, and 1 where this Gaussian would push the transmittance below ``TRANSMITTANCE_MIN`` (the pixel stops before
    it). The one copy of the rule for every forward walk (forward, blend weights, pixel weights), so their weights
    agree bit for bit. The backward kernel replays the same steps inline, because it needs their intermediates
    (``e``, the clamp flag) for the derivatives; the reference tests hold the two to one rule.
    """
    s = ca * dx * dx + cb2 * dx * dy + cc * dy * dy
    inside = _f32(s <= _CUTOFF)
    s_pos = s * _f32(s > _ZERO) * inside  # in [0, cutoff] wherever it matters
    alpha = op * _exp_neg(-_HALF * s_pos)
    over = _f32(alpha > _ALPHA_MAX)
    alpha = alpha + over * (_ALPHA_MAX - alpha)
    m = inside * _f32(alpha >= _ALPHA_MIN) * active
    stop = m * _f32(tr * (_ONE - alpha) < _T_MIN)
    m = m - stop
    return m * alpha * tr, tr * (_ONE - m * alpha), stop


@numba.njit(inline="always", **_JIT)
def _tile_origin(t, tiles_x):
    """Top-left pixel ``(x0, y0)`` of tile ``t`` (tiles numbered row-major)."""
    ty = t // tiles_x
    return (t - ty * tiles_x) * _TILE, ty * _TILE


@numba.njit(inline="always", **_JIT)
def _tile_pixels(t, tiles_x, px, py):
    """Pixel-centre coordinates of tile ``t``'s pixels (row-major) into ``px``, ``py``; returns its origin."""
    x0, y0 = _tile_origin(t, tiles_x)
    for i in range(_TILE_PIXELS):
        px[i] = _f32(x0 + (i % _TILE)) + _HALF
        py[i] = _f32(y0 + (i // _TILE)) + _HALF
    return x0, y0


@numba.njit(inline="always", **_JIT)
def _tile_start(t, tiles_x, width, height):
    """A forward walk's start on tile ``t``: origin ``(x0, y0)``, centres ``px``, ``py``, ``tr`` (ones), ``active``
    (0 for pixels outside the image: they record nothing and do not keep the walk running)."""
    px = np.empty(_TILE_PIXELS, np.float32)
    py = np.empty(_TILE_PIXELS, np.float32)
    x0, y0 = _tile_pixels(t, tiles_x, px, py)
    tr = np.ones(_TILE_PIXELS, np.float32)
    active = np.ones(_TILE_PIXELS, np.float32)
    for i in range(_TILE_PIXELS):
        if x0 + i % _TILE >= width or y0 + i // _TILE >= height:
            active[i] = _ZERO
    return x0, y0, px, py, tr, active


@numba.njit(inline="always", **_JIT)
def _gather_chunk(gids, c0, c1, means2d, conics, opacities, rows, chunk, chunk_rows):
    """The geometry of a tile list's Gaussians ``c0:c1`` copied into small buffers in list order: ``chunk [c, 6]``
    (mean x, y, conic a, doubled b, c, opacity) and ``chunk_rows [c, 2]``. The lists visit the Gaussians in depth
    order, scattered over arrays larger than the cache; independent loads let those misses overlap, where the walk
    would wait for each in turn (``labelmaps_numba`` gathers the same way)."""
    for k in range(c0, c1):
        g = gids[k]
        j = k - c0
        chunk[j, 0] = means2d[g, 0]
        chunk[j, 1] = means2d[g, 1]
        chunk[j, 2] = conics[g, 0]
        chunk[j, 3] = _TWO * conics[g, 1]
        chunk[j, 4] = conics[g, 2]
        chunk[j, 5] = opacities[g]
        chunk_rows[j, 0] = rows[g, 0]
        chunk_rows[j, 1] = rows[g, 1]


@numba.njit(parallel=True, **_JIT)
def _forward_kernel(means2d, conics, opacities, colors, rows, offsets, gids, tiles_x, width, height, accum, trans,
                    stop_pos):
    num_tiles = offsets.shape[0] - 1
    dim = colors.shape[1]
    for t in prange(num_tiles):
        x0, y0, px, py, tr, active = _tile_start(t, tiles_x, width, height)
        start, end = offsets[t], offsets[t + 1]
        stop_k = np.full(_TILE_PIXELS, _f32(end - start), np.float32)
        weight = np.empty(_TILE_PIXELS, np.float32)
        acc = np.zeros((dim, _TILE_PIXELS), np.float32)
        chunk = np.empty((_DONE_CHECK_EVERY, 6), np.float32)  # mx, my, conic a, 2 b, c, opacity
        chunk_rows = np.empty((_DONE_CHECK_EVERY, 2), np.int32)
        chunk_colors = np.empty((_DONE_CHECK_EVERY, dim), np.float32)
        for c0 in range(start, end, _DONE_CHECK_EVERY):
            if c0 > start and active.sum() == _ZERO:
                break
            c1 = min(end, c0 + _DONE_CHECK_EVERY)
            _gather_chunk(gids, c0, c1, means2d, conics, opacities, rows, chunk, chunk_rows)
            for j in range(c1 - c0):
                g = gids[c0 + j]
                chunk_colors[j, :] = colors[g, :]
            for j in range(c1 - c0):
                mx, my, ca, cb2, cc, op = chunk[j, 0], chunk[j, 1], chunk[j, 2], chunk[j, 3], chunk[j, 4], chunk[j, 5]
                kl = _f32(c0 + j - start)
                i0, i1 = _row_range(chunk_rows, j, y0)
                for i in range(i0, i1):
                    weight[i], tr[i], stop = _blend_step(px[i] - mx, py[i] - my, ca, cb2, cc, op, tr[i], active[i])
                    active[i] = active[i] - stop
                    stop_k[i] = stop_k[i] + stop * (kl - stop_k[i])
                for ch in range(dim):
                    col = chunk_colors[j, ch]
                    for i in range(i0, i1):
                        acc[ch, i] += weight[i] * col
        for i in range(_TILE_PIXELS):
            x = x0 + i % _TILE
            y = y0 + i // _TILE
            if x < width and y < height:
                trans[y, x] = tr[i]
                stop_pos[y, x] = np.int32(stop_k[i])
                for ch in range(dim):
                    accum[y, x, ch] = acc[ch, i]


# The backward kernel keeps its per-pixel state in one flat array, one 256-pixel segment per quantity at these
# (unsigned, constant) offsets. As separate arrays, the pixel loop reads and writes so many that LLVM gave up the
# runtime overlap checks its vectorization needed and ran it one pixel at a time; segments of one array at
# constant distances >= the trip count need no check.
_S = np.uint64(_TILE_PIXELS)
_PX, _PY, _STOP, _GFIN, _GALPHA, _TFIN, _TR, _CDOT, _COLDOT, _WEIGHT, _HIT = (np.uint64(q) * _S for q in range(11))
_T0, _T1, _T2, _T3, _T4, _T5 = (np.uint64(11 + q) * _S for q in range(6))  # the six geometry gradient terms
_STATE = 17 * _TILE_PIXELS


@numba.njit(parallel=True, **_JIT)
def _backward_kernel(
    means2d, conics, opacities, colors, rows, offsets, gids, tiles_x, width, height,
    accum, trans, stop_pos, grad_accum, grad_alpha, live_start, slot_geo, slot_col,
):
    """slot_geo[r] = d(mean x, mean y, conic a, b, c, opacity); slot_col[r] = d(colour) of the i-th intersection of
    tile t, stored at r = live_start[t] + i for its live intersections (``_live_slots``) only."""
    num_tiles = offsets.shape[0] - 1
    dim = colors.shape[1]
    for t in prange(num_tiles):
        start, end = offsets[t], offsets[t + 1]
        if end == start:
            continue
        st = np.zeros(_STATE, np.float32)  # per-pixel state, segments at _PX, _PY, ... (above)
        g_acc = np.zeros((dim, _TILE_PIXELS), np.float32)
        x0, y0 = _tile_origin(t, tiles_x)
        for i in range(_TILE_PIXELS):
            u = np.uint64(i)
            x = x0 + i % _TILE
            y = y0 + i // _TILE
            st[_PX + u] = _f32(x) + _HALF
            st[_PY + u] = _f32(y) + _HALF
            st[_TFIN + u] = _ONE
            st[_TR + u] = _ONE
            if x < width and y < height:  # pixels outside the image never blend (stop position 0)
                st[_GALPHA + u] = grad_alpha[y, x]
                st[_TFIN + u] = trans[y, x]
                st[_STOP + u] = _f32(stop_pos[y, x])
                g_final = _ZERO  # C_final . dL/dC
                for ch in range(dim):
                    g_acc[ch, i] = grad_accum[y, x, ch]
                    g_final += accum[y, x, ch] * grad_accum[y, x, ch]
                st[_GFIN + u] = g_final
        slot0 = live_start[t] - start
        for k in range(start, start + (live_start[t + 1] - live_start[t])):
            g = gids[k]
            mx, my = means2d[g, 0], means2d[g, 1]
            ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
            cb2 = _TWO * cb
            op = opacities[g]
            kl = _f32(k - start)
            i0, i1 = _row_range(rows, g, y0)
            for i in range(i0, i1):
                st[_COLDOT + i] = _ZERO
            for ch in range(dim):
                col = colors[g, ch]
                g_acc_ch = g_acc[ch]
                for i in range(i0, i1):
                    st[_COLDOT + i] += col * g_acc_ch[i]
            for i in range(i0, i1):
                dx = st[_PX + i] - mx
                dy = st[_PY + i] - my
                s = ca * dx * dx + cb2 * dx * dy + cc * dy * dy
                inside = _f32(s <= _CUTOFF)
                positive = _f32(s > _ZERO)
                s_pos = s * positive * inside
                e = _exp_neg(-_HALF * s_pos)
                alpha = op * e
                over = _f32(alpha > _ALPHA_MAX)
                alpha = alpha + over * (_ALPHA_MAX - alpha)
                m = inside * _f32(alpha >= _ALPHA_MIN) * _f32(kl < st[_STOP + i])
                tr = st[_TR + i]
                col_dot = st[_COLDOT + i]
                w = m * alpha * tr
                st[_WEIGHT + i] = w
                st[_HIT + i] = m
                c_after = st[_CDOT + i] + w * col_dot
                inv_one_minus = _ONE / (_ONE - alpha)
                d_alpha = tr * col_dot - (st[_GFIN + i] - c_after) * inv_one_minus
                d_alpha = d_alpha + st[_GALPHA + i] * st[_TFIN + i] * inv_one_minus
                d_alpha = d_alpha * m * (_ONE - over)
                d_s = -_HALF * d_alpha * op * e * positive
                st[_T0 + i] = -d_s * (_TWO * ca * dx + cb2 * dy)
                st[_T1 + i] = -d_s * (cb2 * dx + _TWO * cc * dy)
                st[_T2 + i] = d_s * dx * dx
                st[_T3 + i] = d_s * _TWO * dx * dy
                st[_T4 + i] = d_s * dy * dy
                st[_T5 + i] = d_alpha * e
                st[_CDOT + i] = c_after
                st[_TR + i] = tr * (_ONE - m * alpha)
            r = slot0 + k
            if _range_sum(st, _HIT + i0, _HIT + i1) == _ZERO:  # blends at no pixel: all terms zero
                for q in range(6):
                    slot_geo[r, q] = _ZERO
                for ch in range(dim):
                    slot_col[r, ch] = _ZERO
                continue
            slot_geo[r, 0] = _range_sum(st, _T0 + i0, _T0 + i1)
            slot_geo[r, 1] = _range_sum(st, _T1 + i0, _T1 + i1)
            slot_geo[r, 2] = _range_sum(st, _T2 + i0, _T2 + i1)
            slot_geo[r, 3] = _range_sum(st, _T3 + i0, _T3 + i1)
            slot_geo[r, 4] = _range_sum(st, _T4 + i0, _T4 + i1)
            slot_geo[r, 5] = _range_sum(st, _T5 + i0, _T5 + i1)
            for ch in range(dim):
                g_acc_ch = g_acc[ch]
                for i in range(i0, i1):
                    st[_T0 + i] = st[_WEIGHT + i] * g_acc_ch[i]
                slot_col[r, ch] = _range_sum(st, _T0 + i0, _T0 + i1)


@numba.njit(**_JIT)
def _live_slots(offsets, stop_pos, tiles_x, width, height):
    """``live_start [T + 1]``: prefix sum over tiles of each tile's live intersections, the first
    ``min(count, max stop position over its pixels)`` of its list (the rest never blend: every pixel of the tile
    stopped before them). The backward stores gradient slots for those only."""
    num_tiles = offsets.shape[0] - 1
    live = np.zeros(num_tiles + 1, np.int64)
    for t in range(num_tiles):  # serial: one read per pixel (a parallel region costs more at small sizes)
        count = offsets[t + 1] - offsets[t]
        if count == 0:
            continue
        x0, y0 = _tile_origin(t, tiles_x)
        max_stop = 0
        for y in range(y0, min(height, y0 + _TILE)):
            for x in range(x0, min(width, x0 + _TILE)):
                max_stop = max(max_stop, np.int64(stop_pos[y, x]))
        live[t + 1] = min(count, max_stop)
    for t in range(num_tiles):
        live[t + 1] += live[t]
    return live


@numba.njit(**_JIT)
def _sum_part(offsets, gids, live_start, slot_geo, slot_col, g_lo, g_hi, geo, col):
    for t in range(offsets.shape[0] - 1):
        r0 = live_start[t]
        k0 = offsets[t]
        for i in range(live_start[t + 1] - r0):
            g = gids[k0 + i]
            if g >= g_lo and g < g_hi:
                r = r0 + i
                for c in range(6):
                    geo[g, c] += slot_geo[r, c]
                for c in range(slot_col.shape[1]):
                    col[g, c] += slot_col[r, c]


@numba.njit(parallel=True, **_JIT)
def _sum_slots(offsets, gids, live_start, slot_geo, slot_col, num_gaussians, num_parts):
    """Fixed-order sum of the live gradient slots into per-Gaussian gradients (float64).

    Every Gaussian's slots are added in increasing tile order, whatever the thread count: part p (parallel) owns a
    contiguous range of Gaussian indices and walks all live slots in tile order, adding only its own.
    """
    geo = np.zeros((num_gaussians, 6), np.float64)
    col = np.zeros((num_gaussians, slot_col.shape[1]), np.float64)
    per = (num_gaussians + num_parts - 1) // num_parts
    for p in prange(num_parts):
        _sum_part(offsets, gids, live_start, slot_geo, slot_col, p * per, (p + 1) * per, geo, col)
    return geo, col


@numba.njit(parallel=True, **_JIT)
def _weights_kernel(means2d, conics, opacities, rows, offsets, gids, tiles_x, width, height, ids, weights, residual):
    num_tiles = offsets.shape[0] - 1
    top_k = ids.shape[2]
    for t in prange(num_tiles):
        x0, y0, px, py, tr, active = _tile_start(t, tiles_x, width, height)
        start, end = offsets[t], offsets[t + 1]
        weight = np.empty(_TILE_PIXELS, np.float32)
        count = np.zeros(_TILE_PIXELS, np.int64)
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
            for i in range(i0, i1):
                if weight[i] > _ZERO:
                    x = x0 + i % _TILE
                    y = y0 + i // _TILE
                    if count[i] < top_k:
                        ids[y, x, count[i]] = g
                        weights[y, x, count[i]] = weight[i]
                        count[i] += 1
                    else:
                        residual[y, x] += weight[i]


def _as_np(x: Tensor) -> np.ndarray:
    """float32 contiguous numpy copy/view (converted by numpy: no torch thread synchronization)."""
    return np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)


class _BlendFunction(torch.autograd.Function):
    """(means2d, conics, opacities, colors) -> (accumulated colours [H, W, D], accumulated alpha [H, W])."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, bins: TileBins):
        m2, cn, op, col = (_as_np(x) for x in (means2d, conics, opacities, colors))
        h, w, dim = bins.height, bins.width, col.shape[1]
        accum = np.zeros((h, w, dim), np.float32)
        trans = np.ones((h, w), np.float32)
        stop_pos = np.zeros((h, w), np.int32)
        if bins.num_intersections:
            run_parallel(
                _forward_kernel, m2, cn, op, col, bins.rows, bins.offsets, bins.gaussian_ids, bins.tiles_x, w, h,
                accum, trans, stop_pos,
            )
        ctx.bins = bins
        ctx.arrays = (m2, cn, op, col, accum, trans, stop_pos)
        ctx.dtypes = (means2d.dtype, conics.dtype, opacities.dtype, colors.dtype)
        return torch.from_numpy(accum), torch.from_numpy(1.0 - trans)

    @staticmethod
    def backward(ctx, grad_accum, grad_alpha):
        bins: TileBins = ctx.bins
        m2, cn, op, col, accum, trans, stop_pos = ctx.arrays
        n, dim = m2.shape[0], col.shape[1]
        g_acc = np.zeros_like(accum) if grad_accum is None else _as_np(grad_accum)
        g_alpha = np.zeros_like(trans) if grad_alpha is None else _as_np(grad_alpha)
        live_start = _live_slots(bins.offsets, stop_pos, bins.tiles_x, bins.width, bins.height)
        num = int(live_start[-1])
        slot_geo = np.empty((num, 6), np.float32)  # every live slot is written by the kernel
        slot_col = np.empty((num, dim), np.float32)
        if num:
            run_parallel(
                _backward_kernel, m2, cn, op, col, bins.rows, bins.offsets, bins.gaussian_ids, bins.tiles_x,
                bins.width, bins.height, accum, trans, stop_pos, g_acc, g_alpha, live_start, slot_geo, slot_col,
            )
        # chunk=0 (numba's default): a chunk size also applies to the kernel's implicit parallel zero-fills, which
        # with chunk=1 took seconds at 1M Gaussians
        geo, dcol = run_parallel(_sum_slots, bins.offsets, bins.gaussian_ids, live_start, slot_geo, slot_col, n,
                                 max(1, numba.get_num_threads()), chunk=0)
        geo = torch.from_numpy(geo)
        d_means2d = geo[:, 0:2].to(ctx.dtypes[0])
        d_conics = geo[:, 2:5].to(ctx.dtypes[1])
        d_opacities = geo[:, 5].to(ctx.dtypes[2])
        d_colors = torch.from_numpy(dcol).to(ctx.dtypes[3])
        return d_means2d, d_conics, d_opacities, d_colors, None


def blend_fast(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D]
    bins: TileBins,
) -> tuple[Tensor, Tensor]:  # accumulated colours [H, W, D] float32, accumulated alpha [H, W] float32
    """Front-to-back blending with the numba kernels; differentiable (custom autograd Function)."""
    return _BlendFunction.apply(means2d, conics, opacities, colors, bins)


def blend_weights_fast(
    means2d: Tensor, conics: Tensor, opacities: Tensor, bins: TileBins, top_k: int
) -> BlendWeights:
    """The first ``top_k`` blend weights per pixel (same walk as the forward kernel)."""
    h, w = bins.height, bins.width
    ids = np.full((h, w, top_k), -1, np.int64)
    weights = np.zeros((h, w, top_k), np.float32)
    residual = np.zeros((h, w), np.float32)
    if bins.num_intersections:
        run_parallel(
            _weights_kernel, _as_np(means2d), _as_np(conics), _as_np(opacities), bins.rows, bins.offsets, bins.gaussian_ids,
            bins.tiles_x, w, h, ids, weights, residual,
        )
    return BlendWeights(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(residual))
