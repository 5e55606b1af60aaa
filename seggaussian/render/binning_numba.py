"""Binning kernels (numba): a stable parallel radix sort by depth, then a parallel counting sort into tiles.

No comparison sort anywhere:

1. Depth sort (``_radix_sort``): each selected Gaussian (in index order) becomes one uint64, the top bits of a key
   that orders exactly as its float64 depth (the usual sign-flip of the IEEE bits; +0 and -0 equal, NaN last),
   minus the smallest key, above the bits of its position. LSD radix passes of ``RADIX_BITS``-bit digits cover
   only the top bits of the key range (enough to spread n keys over about 4 n buckets: 2 passes at 1M), each
   parallel over chunks (per-chunk digit histograms, an exclusive prefix sum digit-major then chunk-major, a
   scatter) and moving 8 bytes per element; runs of equal sorted bits are then ordered by their packed words (the
   key bits below the sorted ones, then the position; short insertion sorts in cache), and only words that share
   every packed key bit by the full key. LSD radix sorting is stable, so equal depths keep index order, exactly as
   the former ``argsort(kind="stable")``.
2. Tile lists: the depth-sorted Gaussians are split into chunks; each chunk counts its intersections per tile
   (four corner updates of a 2D difference array per box, or per tile row of a box the ellipse cull trimmed, then a
   2D prefix sum), a prefix sum over (tile, chunk) gives every chunk its write cursor in every tile, and the chunks
   scatter in parallel. Chunk c's entries of a tile precede chunk c + 1's and keep their order within the chunk, so
   every tile's list is in depth order with no per-tile sort.

Ellipse culling (``bin_sorted`` given the 2D means, conics and opacities): a Gaussian goes only to the tiles of its
box that its blending ellipse reaches (``ellipse_cull``: the box shrunk to the ellipse, and up to ``MAX_TRIM`` tiles
trimmed on each side of its first ``TRIM_ROWS`` tile rows, packed into the box word). A dropped (Gaussian, tile)
pair blends at no pixel of the tile, so images, blend weights and gradients are those of the whole boxes, with fewer
pairs to store and walk.

The result is independent of the thread count: integer arithmetic, and per-Gaussian float64 in the cull.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from seggaussian.core.constants import TILE_SIZE
from seggaussian.render.ellipse_cull import (
    LANE_FIELDS,
    TRIM_ROWS,
    TRIMS,
    TX0,
    TX1,
    TY0,
    TY1,
    cull_lanes,
    cull_radius2,
    stage,
)
from seggaussian.render.parallel import GAUSSIANS_PER_CHUNK, run_parallel
from seggaussian.render.projection_lanes import LANE_BLOCK, new_block

_JIT = dict(cache=True, nogil=True)

#: Bits per radix digit (2048 buckets: the per-chunk histograms and scatter targets stay in L1/L2).
RADIX_BITS = 11
_RADIX = 1 << RADIX_BITS
_U1 = np.uint64(1)
_MASK = np.uint64(_RADIX - 1)
_SIGN = np.uint64(1 << 63)
_ALL = np.uint64(0xFFFFFFFFFFFFFFFF)
_ABS = np.uint64(0x7FFFFFFFFFFFFFFF)
_INF_BITS = np.uint64(0x7FF0000000000000)
_ZERO = np.uint64(0)
_EMPTY_U64 = np.empty(0, np.uint64)
_EMPTY_F32 = np.empty(0, np.float32)
#: Radix passes cover at least this many top bits of the key range (more for more keys: log2(n) + 2).
_MIN_TOP_BITS = 16
#: Runs of equal top bits up to this long are ordered by insertion sort, longer ones by a merge sort.
_INSERTION_MAX = 32
#: Tile boxes are packed as four 12-bit coordinates and 16 bits of row trims (``_pack_box``): at most this many
#: tiles per side (images up to 65,520 pixels wide and high; an empty box's first row is its last plus one).
MAX_TILES_PER_SIDE = (1 << 12) - 1
#: Work chunks per thread in the sort and binning kernels (a few, so that uneven chunks balance).
CHUNKS_PER_THREAD = 4


@numba.njit(parallel=True, **_JIT)
def _boxes_and_keys(idx, pixel_box, tile_size, depth_bits):
    """Packed tile boxes and depth keys (``_depth_key``) of the Gaussians ``idx`` (one pass, read front to back)."""
    n = idx.shape[0]
    boxes = np.empty(n, np.uint64)
    keys = np.empty(n, np.uint64)
    for j in prange(n):
        g = idx[j]
        boxes[j] = _pack_box(pixel_box[g, 0] // tile_size, pixel_box[g, 1] // tile_size,
                             pixel_box[g, 2] // tile_size, pixel_box[g, 3] // tile_size, 0)
        keys[j] = _depth_key(depth_bits[g])
    return boxes, keys


@numba.njit(parallel=True, **_JIT)
def _culled_boxes_and_keys(idx, pixel_box, means2d, conics, opacities, depth_bits):
    """``_boxes_and_keys`` with the ellipse cull: the packed tile boxes shrunk to each blending ellipse with their
    row trims (``ellipse_cull.cull_lanes``, blocks of LANE_BLOCK Gaussians), and the depth keys. ``opacities`` empty:
    the 3-sigma ellipse alone."""
    n = idx.shape[0]
    boxes = np.empty(n, np.uint64)
    keys = np.empty(n, np.uint64)
    lb = np.uint64(LANE_BLOCK)
    with_opacity = opacities.shape[0] > 0
    for block in prange((n + LANE_BLOCK - 1) // LANE_BLOCK):
        lane, lo, count = new_block(block, LANE_FIELDS, n)  # unused lanes: a degenerate conic, never read
        for i in range(count):
            g = idx[lo + i]
            stage(lane, i, pixel_box[g, 0], pixel_box[g, 1], pixel_box[g, 2], pixel_box[g, 3], means2d[g, 0],
                  means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2],
                  cull_radius2(np.float64(opacities[g]) if with_opacity else -1.0))
        cull_lanes(lane)
        for i in range(count):
            boxes[lo + i] = _pack_box(np.int64(lane[TX0 * lb + i]), np.int64(lane[TY0 * lb + i]),
                                      np.int64(lane[TX1 * lb + i]), np.int64(lane[TY1 * lb + i]),
                                      np.int64(lane[TRIMS * lb + i]))
            keys[lo + i] = _depth_key(depth_bits[idx[lo + i]])
    return boxes, keys


@numba.njit(inline="always", **_JIT)
def _row_span(trims, k, tx0, tx1):
    """Inclusive tile columns ``(first, last)`` of the box's k-th tile row after its trims (empty: first > last).
    No branch: rows from TRIM_ROWS on shift the 16 trim bits out."""
    b = (trims >> (4 * min(k, TRIM_ROWS))) & 15
    return tx0 + (b & 3), tx1 - (b >> 2)


@numba.njit(parallel=True, **_JIT)
def _depth_keys(idx, depth_bits):
    """Depth keys (``_depth_key``) of the Gaussians ``idx``."""
    keys = np.empty(idx.shape[0], np.uint64)
    for j in prange(idx.shape[0]):
        keys[j] = _depth_key(depth_bits[idx[j]])
    return keys


@numba.njit(inline="always", **_JIT)
def _depth_key(bits):
    """Sortable uint64 key of a float64 depth given as its IEEE bits: unsigned order == float order; -0 and +0 one
    key; every NaN sorts last (as in numpy)."""
    magnitude = bits & _ABS
    if magnitude > _INF_BITS:  # NaN
        return _ALL
    if magnitude == _ZERO:  # +0 or -0
        return _SIGN
    if bits & _SIGN:
        return bits ^ _ALL
    return bits | _SIGN


@numba.njit(inline="always", **_JIT)
def _pack_box(tx0, ty0, tx1, ty1, trims):
    """Inclusive tile box (each coordinate < 2^12) and its 16 bits of row trims (row k's left trim in bits 4k..4k+1,
    its right trim in 4k+2..4k+3; 0: the whole row) as one uint64."""
    return (np.uint64(tx0) | (np.uint64(ty0) << np.uint64(12)) | (np.uint64(tx1) << np.uint64(24))
            | (np.uint64(ty1) << np.uint64(36)) | (np.uint64(trims) << np.uint64(48)))


@numba.njit(inline="always", **_JIT)
def _unpack_box(b):
    """``(tx0, ty0, tx1, ty1, trims)`` of a packed box (int64)."""
    m = np.uint64(0xFFF)
    return (np.int64(b & m), np.int64((b >> np.uint64(12)) & m), np.int64((b >> np.uint64(24)) & m),
            np.int64((b >> np.uint64(36)) & m), np.int64(b >> np.uint64(48)))


# The per-chunk loops are plain (non-parallel) functions called from the prange bodies: LLVM optimizes them as
# ordinary loops (written inline in a prange body, the same loops ran several times slower).


@numba.njit(**_JIT)
def _digit_histogram(keys, lo, hi, shift, hist):
    hist[:] = 0
    for j in range(lo, hi):
        hist[(keys[j] >> shift) & _MASK] += 1


@numba.njit(**_JIT)
def _digit_scatter(keys, lo, hi, shift, cursor, keys_out):
    for j in range(lo, hi):
        k = keys[j]
        d = (k >> shift) & _MASK
        p = cursor[d]
        cursor[d] = p + 1
        keys_out[p] = k


@numba.njit(**_JIT)
def _count_chunk(boxes, lo, hi, tiles_x, counts):
    """Intersections per tile of the boxes ``lo:hi`` (with their row trims):
    four corner updates of a 2D difference array per untrimmed box, two per tile row of a trimmed one (no loop over
    a row's tiles, whose varying trip counts mispredict), then a 2D prefix sum."""
    tiles_y = counts.shape[0] // tiles_x
    stride = tiles_x + 1
    diff = np.zeros((tiles_y + 1) * stride, np.int64)
    for j in range(lo, hi):
        tx0, ty0, tx1, ty1, tr = _unpack_box(boxes[j])
        if tr == 0:
            if ty0 <= ty1:
                r0 = ty0 * stride
                r1 = (ty1 + 1) * stride
                diff[r0 + tx0] += 1
                diff[r0 + tx1 + 1] -= 1
                diff[r1 + tx0] -= 1
                diff[r1 + tx1 + 1] += 1
            continue
        for ty in range(ty0, ty1 + 1):  # a row's span [a, b]: +1 at (ty, a) and below it -1, the same at b + 1
            a, b = _row_span(tr, ty - ty0, tx0, tx1)
            if a <= b:
                r0 = ty * stride
                r1 = r0 + stride
                diff[r0 + a] += 1
                diff[r0 + b + 1] -= 1
                diff[r1 + a] -= 1
                diff[r1 + b + 1] += 1
    for ty in range(tiles_y):
        run = 0
        for tx in range(tiles_x):
            run += diff[ty * stride + tx]
            above = counts[(ty - 1) * tiles_x + tx] if ty > 0 else 0
            counts[ty * tiles_x + tx] = run + above


@numba.njit(**_JIT)
def _scatter_chunk(order, boxes, lo, hi, tiles_x, cursor, ids):
    """Append the Gaussians ``lo:hi`` to the tiles of their (trimmed) boxes at ``cursor``. The tile and slot indices
    are unsigned: numba then emits no negative-index wraparound per access (the scatter of 1M Gaussians took 31 -> 22
    ms); a row is entered only when its span is not empty, so no index
    wraps."""
    for j in range(lo, hi):
        g = np.int32(order[j])
        tx0, ty0, tx1, ty1, tr = _unpack_box(boxes[j])
        for ty in range(ty0, ty1 + 1):
            a, b = (tx0, tx1) if tr == 0 else _row_span(tr, ty - ty0, tx0, tx1)
            if a <= b:
                row = np.uint64(ty * tiles_x)
                for tx in range(np.uint64(a), np.uint64(b + 1)):
                    t = row + tx
                    p = cursor[t]
                    cursor[t] = p + 1
                    ids[np.uint64(p)] = g


@numba.njit(**_JIT)
def _bit_length(x):
    bits = 0
    while x > _ZERO:
        x = x >> _U1
        bits += 1
    return bits


@numba.njit(**_JIT)
def _sort_words(packed, start, end):
    """Sort ``packed[start:end]`` ascending as uint64 (the words are distinct: each holds its position): insertion
    sort when short, numpy's sort otherwise."""
    if end - start > _INSERTION_MAX:
        packed[start:end] = np.sort(packed[start:end])
        return
    for i in range(start + 1, end):
        v = packed[i]
        j = i - 1
        while j >= start and packed[j] > v:
            packed[j + 1] = packed[j]
            j -= 1
        packed[j + 1] = v


@numba.njit(**_JIT)
def _order_by_full_key(packed, start, end, keys, pos_mask):
    """Stable sort of ``packed[start:end]`` (in position order) by ``keys[position]``: insertion sort when short,
    a merge sort otherwise."""
    if end - start <= _INSERTION_MAX:
        for i in range(start + 1, end):
            v = packed[i]
            k = keys[v & pos_mask]
            j = i - 1
            while j >= start and keys[packed[j] & pos_mask] > k:
                packed[j + 1] = packed[j]
                j -= 1
            packed[j + 1] = v
        return
    run = packed[start:end].copy()
    full = np.empty(end - start, np.uint64)
    for i in range(end - start):
        full[i] = keys[run[i] & pos_mask]
    perm = np.argsort(full, kind="mergesort")
    for i in range(end - start):
        packed[start + i] = run[perm[i]]


@numba.njit(inline="always", **_JIT)
def _run_end(packed, start, hi, shift):
    """End (exclusive, at most ``hi``) of the run of words whose bits above ``shift`` equal ``packed[start]``'s."""
    top = packed[start] >> shift
    end = start + 1
    while end < hi and (packed[end] >> shift) == top:
        end += 1
    return end


@numba.njit(**_JIT)
def _fix_runs_between(packed, keys, lo, hi, pos_bits, sorted_shift, dropped):
    """``_fix_runs`` on ``packed[lo:hi]``, which starts and ends on run boundaries."""
    pos_mask = (_U1 << np.uint64(pos_bits)) - _U1
    us = np.uint64(sorted_shift)
    up = np.uint64(pos_bits)
    start = lo
    while start < hi:
        end = _run_end(packed, start, hi, us)
        if end - start > 1:
            if sorted_shift > pos_bits:  # kept bits below the sorted ones: order by the whole word
                _sort_words(packed, start, end)
            if dropped:  # equal kept bits, positions ascending: the full key decides
                s = start
                while s < end:
                    e = _run_end(packed, s, end, up)
                    if e - s > 1:
                        _order_by_full_key(packed, s, e, keys, pos_mask)
                    s = e
        start = end


@numba.njit(parallel=True, **_JIT)
def _fix_runs(packed, keys, pos_bits, sorted_shift, dropped, num_chunks):
    """Order every run of equal ``packed >> sorted_shift`` (the bits the radix passes sorted) by (full key,
    position): the order a stable sort by the full key gives.

    A packed word holds the key's top bits above its position, so sorting a run by the packed words themselves
    (which are in cache) orders it by (kept key bits, position) without reading ``keys``. Only where ``dropped``
    (key bits did not fit the word) and two words share every kept bit does the full key decide, read from ``keys``
    (the random reads that dominated this pass when every run was ordered by its full keys). Runs are disjoint, so
    chunks that start on run boundaries are fixed in parallel (the result does not depend on the chunking).
    """
    n = packed.shape[0]
    us = np.uint64(sorted_shift)
    size = (n + num_chunks - 1) // num_chunks
    bounds = np.empty(num_chunks + 1, np.int64)
    bounds[num_chunks] = n
    for c in prange(num_chunks):
        b = min(n, c * size)
        while 0 < b < n and (packed[b] >> us) == (packed[b - 1] >> us):
            b += 1  # move forward to the start of a run
        bounds[c] = b
    for c in prange(num_chunks):
        hi = bounds[c + 1]
        if hi > bounds[c]:
            _fix_runs_between(packed, keys, bounds[c], hi, pos_bits, sorted_shift, dropped)


@numba.njit(parallel=True, **_JIT)
def _radix_sort(keys, idx, boxes, num_chunks):
    """``(idx[pos], boxes[pos])`` for the positions ``pos`` that sort ``keys`` (uint64) stably.

    Each element is one uint64: the top bits of ``key - min`` above its position's bits, so every radix pass moves
    8 bytes per element and the position rides along for free. LSD passes of ``RADIX_BITS``-bit digits cover the
    top bits of the key range only: enough to spread ``n`` keys over about 4 n buckets. ``_fix_runs`` then orders
    each run of equal sorted bits (runs are short unless many keys share their top bits).
    """
    n = keys.shape[0]
    lo_key = keys.min()
    span_bits = _bit_length(keys.max() - lo_key)
    pos_bits = max(1, _bit_length(np.uint64(n - 1)))
    kept_bits = min(span_bits, 64 - pos_bits)  # key bits stored in the packed word
    drop = np.uint64(span_bits - kept_bits)
    wanted = max(_MIN_TOP_BITS, _bit_length(np.uint64(n)) + 2)
    passes = (min(kept_bits, wanted) + RADIX_BITS - 1) // RADIX_BITS
    sorted_shift = pos_bits + max(0, kept_bits - passes * RADIX_BITS)
    ub = np.uint64(pos_bits)
    k_a = np.empty(n, np.uint64)
    for j in prange(n):
        k_a[j] = (((keys[j] - lo_key) >> drop) << ub) | np.uint64(j)
    k_b = np.empty(n, np.uint64)
    size = (n + num_chunks - 1) // num_chunks
    hist = np.empty((num_chunks, _RADIX), np.int64)
    for pas in range(passes):
        shift = np.uint64(sorted_shift + pas * RADIX_BITS)
        for c in prange(num_chunks):
            _digit_histogram(k_a, c * size, min(n, (c + 1) * size), shift, hist[c])
        total = 0
        for d in range(_RADIX):
            for c in range(num_chunks):
                cnt = hist[c, d]
                hist[c, d] = total
                total += cnt
        for c in prange(num_chunks):
            _digit_scatter(k_a, c * size, min(n, (c + 1) * size), shift, hist[c], k_b)
        k_a, k_b = k_b, k_a
    if drop > 0 or sorted_shift > pos_bits:  # key bits below the sorted ones
        _fix_runs(k_a, keys, pos_bits, sorted_shift, drop > 0, num_chunks)
    pos_mask = (_U1 << ub) - _U1
    order = np.empty(n, np.int64)
    sorted_boxes = np.empty(boxes.shape[0], np.uint64)  # empty when no boxes are given
    with_boxes = boxes.shape[0] > 0
    for j in prange(n):
        p = np.int64(k_a[j] & pos_mask)
        order[j] = idx[p]
        if with_boxes:
            sorted_boxes[j] = boxes[p]
    return order, sorted_boxes


@numba.njit(parallel=True, **_JIT)
def _count_tiles(boxes, tiles_x, num_tiles, num_chunks):
    """Per-chunk intersection counts [chunks, tiles] of the packed tile boxes (in depth order)."""
    m = boxes.shape[0]
    counts = np.zeros((num_chunks, num_tiles), np.int64)
    size = (m + num_chunks - 1) // num_chunks
    for c in prange(num_chunks):
        _count_chunk(boxes, c * size, min(m, (c + 1) * size), tiles_x, counts[c])
    return counts


@numba.njit(parallel=True, **_JIT)
def _scatter_tiles(order, boxes, counts, tiles_x, num_tiles):
    """CSR offsets [T + 1] and ids [I]; ``counts`` becomes each chunk's write cursor per tile."""
    num_chunks = counts.shape[0]
    offsets = np.empty(num_tiles + 1, np.int64)
    total = 0
    for t in range(num_tiles):
        offsets[t] = total
        for c in range(num_chunks):
            cnt = counts[c, t]
            counts[c, t] = total
            total += cnt
    offsets[num_tiles] = total
    m = order.shape[0]
    ids = np.empty(total, np.int32)
    size = (m + num_chunks - 1) // num_chunks
    for c in prange(num_chunks):
        _scatter_chunk(order, boxes, c * size, min(m, (c + 1) * size), tiles_x, counts[c], ids)
    return offsets, ids


def _num_chunks(n: int) -> int:
    return max(1, min(CHUNKS_PER_THREAD * numba.get_num_threads(), n // 1024 + 1))


def depth_order(idx: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """``idx`` (ascending int64 indices) sorted stably by ``depths[idx]`` (float64), as int64."""
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if idx.shape[0] < 2:
        return idx.copy()
    depth_bits = np.ascontiguousarray(depths, dtype=np.float64).view(np.uint64)
    keys = run_parallel(_depth_keys, idx, depth_bits, chunk=GAUSSIANS_PER_CHUNK)
    order, _ = run_parallel(_radix_sort, keys, idx, _EMPTY_U64, _num_chunks(idx.shape[0]), chunk=0)
    return order


def bin_sorted(idx: np.ndarray, depths: np.ndarray, pixel_box: np.ndarray, tile_size: int, tiles_x: int,
               tiles_y: int, means2d: np.ndarray | None = None, conics: np.ndarray | None = None,
               opacities: np.ndarray | None = None):
    """CSR tile lists of the Gaussians ``idx`` (ascending), each tile's list by increasing depth (ties: index).

    Without ``means2d`` and ``conics`` every Gaussian goes to every tile its inclusive pixel box ``(u0, v0, u1, v1)``
    touches. With them (``[N, 2]``, ``[N, 3]`` float64, and optionally ``opacities`` ``[N]``), only to the tiles of
    that box its blending ellipse reaches (the module's "Ellipse culling"). The packed tile boxes ride along in the
    depth sort, so no step reads ``pixel_box`` in depth (random) order.
    Returns (offsets [T + 1] int64, ids [I] int32, order [M] int64: the Gaussians by depth).
    """
    num_tiles = tiles_x * tiles_y
    if max(tiles_x, tiles_y) > MAX_TILES_PER_SIDE:
        raise ValueError(f"bin_sorted: at most {MAX_TILES_PER_SIDE} tiles per side, got {tiles_x} x {tiles_y}")
    if (means2d is None) != (conics is None) or (opacities is not None and means2d is None):
        raise ValueError("bin_sorted: give means2d and conics together (and opacities only with them)")
    if means2d is not None and tile_size != TILE_SIZE:
        raise ValueError(f"bin_sorted: the ellipse cull needs tile_size {TILE_SIZE}, got {tile_size}")
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if idx.shape[0] == 0:
        return np.zeros(num_tiles + 1, np.int64), np.zeros(0, np.int32), idx
    pixel_box = np.ascontiguousarray(pixel_box, dtype=np.int64)
    depth_bits = np.ascontiguousarray(depths, dtype=np.float64).view(np.uint64)
    if means2d is None:
        boxes, keys = run_parallel(_boxes_and_keys, idx, pixel_box, tile_size, depth_bits, chunk=GAUSSIANS_PER_CHUNK)
    else:
        boxes, keys = run_parallel(
            _culled_boxes_and_keys, idx, pixel_box, np.ascontiguousarray(means2d, dtype=np.float64),
            np.ascontiguousarray(conics, dtype=np.float64),
            _EMPTY_F32 if opacities is None else np.ascontiguousarray(opacities, dtype=np.float32), depth_bits,
            chunk=max(1, GAUSSIANS_PER_CHUNK // LANE_BLOCK))
    if idx.shape[0] > 1:
        idx, boxes = run_parallel(_radix_sort, keys, idx, boxes, _num_chunks(idx.shape[0]), chunk=0)
    chunks = _num_chunks(idx.shape[0])
    counts = run_parallel(_count_tiles, boxes, tiles_x, num_tiles, chunks, chunk=0)
    offsets, ids = run_parallel(_scatter_tiles, idx, boxes, counts, tiles_x, num_tiles, chunk=0)
    return offsets, ids, idx
