"""Binning kernels (numba): a stable parallel radix sort by depth, then a parallel counting sort into tiles.

No comparison sort anywhere:

1. ``depth_order``: the selected Gaussians (in index order) are sorted by an unsigned 64-bit key that orders
   exactly as their float64 depths (the usual sign-flip of the IEEE bits; +0 and -0 equal, NaN last), minus the
   smallest key, with an LSD radix sort of ``RADIX_BITS``-bit digits: only as many passes as the key range has
   digits (5 for the depths of a real scene). Each pass is parallel over chunks: per-chunk digit histograms, an
   exclusive prefix sum (digit-major, then chunk-major), a scatter. LSD radix sorting is stable, so equal depths
   keep index order, exactly as the former ``argsort(kind="stable")``.
2. ``tile_lists``: the depth-sorted Gaussians are split into chunks; each chunk counts its intersections per tile
   (and stores its tile boxes), a prefix sum over (tile, chunk) gives every chunk its write cursor in every tile,
   and the chunks scatter in parallel. Chunk c's entries of a tile precede chunk c + 1's and keep their order
   within the chunk, so every tile's list is in depth order with no per-tile sort.

Integer arithmetic only: the result is independent of the thread count.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from seggaussian.render.rasterize_numba import GAUSSIANS_PER_CHUNK, run_parallel

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
#: Radix passes cover at least this many top bits of the key range (more for more keys: log2(n) + 2).
_MIN_TOP_BITS = 16
#: Runs of equal top bits up to this long are ordered by insertion sort, longer ones by a merge sort.
_INSERTION_MAX = 32
#: Tile boxes are packed as four 16-bit coordinates.
MAX_TILES_PER_SIDE = 1 << 16
#: Work chunks per thread in the sort and binning kernels (a few, so that uneven chunks balance).
CHUNKS_PER_THREAD = 4


@numba.njit(parallel=True, **_JIT)
def _tile_boxes(idx, pixel_box, tile_size):
    """Packed tile boxes of the Gaussians ``idx`` (ascending: pixel_box is read front to back)."""
    boxes = np.empty(idx.shape[0], np.uint64)
    for j in prange(idx.shape[0]):
        g = idx[j]
        boxes[j] = _pack_box(pixel_box[g, 0] // tile_size, pixel_box[g, 1] // tile_size,
                             pixel_box[g, 2] // tile_size, pixel_box[g, 3] // tile_size)
    return boxes


@numba.njit(parallel=True, **_JIT)
def _depth_keys(idx, depth_bits):
    """Sortable uint64 keys of the float64 depths (given as their IEEE bits) at ``idx``: unsigned order ==
    float order; -0 and +0 one key; every NaN sorts last (as in numpy)."""
    n = idx.shape[0]
    keys = np.empty(n, np.uint64)
    for j in prange(n):
        bits = depth_bits[idx[j]]
        magnitude = bits & _ABS
        if magnitude > _INF_BITS:  # NaN
            keys[j] = _ALL
        elif magnitude == _ZERO:  # +0 or -0
            keys[j] = _SIGN
        elif bits & _SIGN:
            keys[j] = bits ^ _ALL
        else:
            keys[j] = bits | _SIGN
    return keys


@numba.njit(inline="always", **_JIT)
def _pack_box(tx0, ty0, tx1, ty1):
    """Inclusive tile box (each coordinate < 2^16) as one uint64."""
    return (np.uint64(tx0) | (np.uint64(ty0) << np.uint64(16)) | (np.uint64(tx1) << np.uint64(32))
            | (np.uint64(ty1) << np.uint64(48)))


@numba.njit(inline="always", **_JIT)
def _unpack_box(b):
    m = np.uint64(0xFFFF)
    return (np.int64(b & m), np.int64((b >> np.uint64(16)) & m), np.int64((b >> np.uint64(32)) & m),
            np.int64(b >> np.uint64(48)))


# The per-chunk loops are plain (non-parallel) functions called from the prange bodies: LLVM optimizes them as
# ordinary loops (written inline in a prange body, the same loops ran several times slower).


@numba.njit(**_JIT)
def _digit_histogram(keys, lo, hi, shift, hist):
    hist[:] = 0
    for j in range(lo, hi):
        hist[(keys[j] >> shift) & _MASK] += 1


@numba.njit(**_JIT)
def _digit_scatter(keys, vals, extra, lo, hi, shift, cursor, keys_out, vals_out, extra_out):
    with_extra = extra.shape[0] > 0
    for j in range(lo, hi):
        k = keys[j]
        d = (k >> shift) & _MASK
        p = cursor[d]
        cursor[d] = p + 1
        keys_out[p] = k
        vals_out[p] = vals[j]
        if with_extra:
            extra_out[p] = extra[j]


@numba.njit(**_JIT)
def _count_chunk(boxes, lo, hi, tiles_x, counts):
    for j in range(lo, hi):
        tx0, ty0, tx1, ty1 = _unpack_box(boxes[j])
        for ty in range(ty0, ty1 + 1):
            row = ty * tiles_x
            for tx in range(tx0, tx1 + 1):
                counts[row + tx] += 1


@numba.njit(**_JIT)
def _scatter_chunk(order, boxes, lo, hi, tiles_x, cursor, ids, isect_start, slot_rank):
    for j in range(lo, hi):
        g = np.int32(order[j])
        q = isect_start[j]
        tx0, ty0, tx1, ty1 = _unpack_box(boxes[j])
        for ty in range(ty0, ty1 + 1):
            row = ty * tiles_x
            for tx in range(tx0, tx1 + 1):
                t = row + tx
                p = cursor[t]
                cursor[t] = p + 1
                ids[p] = g
                slot_rank[p] = q
                q += 1


@numba.njit(**_JIT)
def _bit_length(x):
    bits = 0
    while x > _ZERO:
        x = x >> _U1
        bits += 1
    return bits


@numba.njit(**_JIT)
def _fix_runs(keys, vals, extra, drop):
    """Stable sort by the full key of every run of equal ``key >> drop`` (the radix passes sorted those bits).

    Runs are short where depths are spread (insertion sort); a long run of distinct keys gets a stable merge sort.
    """
    n = keys.shape[0]
    with_extra = extra.shape[0] > 0
    ud = np.uint64(drop)
    start = 0
    while start < n:
        top = keys[start] >> ud
        end = start + 1
        while end < n and (keys[end] >> ud) == top:
            end += 1
        if end - start > 1:
            if end - start <= _INSERTION_MAX:
                for i in range(start + 1, end):
                    k, v = keys[i], vals[i]
                    e = extra[i] if with_extra else _ZERO
                    j = i - 1
                    while j >= start and keys[j] > k:
                        keys[j + 1] = keys[j]
                        vals[j + 1] = vals[j]
                        if with_extra:
                            extra[j + 1] = extra[j]
                        j -= 1
                    keys[j + 1] = k
                    vals[j + 1] = v
                    if with_extra:
                        extra[j + 1] = e
            else:
                perm = np.argsort(keys[start:end], kind="mergesort")
                run_k = keys[start:end][perm]
                run_v = vals[start:end][perm]
                keys[start:end] = run_k
                vals[start:end] = run_v
                if with_extra:
                    extra[start:end] = extra[start:end][perm]
        start = end


@numba.njit(parallel=True, **_JIT)
def _radix_sort(keys, vals, extra, num_chunks):
    """Stable sort of ``vals`` (and ``extra``, a second uint64 payload, unless empty) by ``keys`` (uint64);
    returns the sorted (vals, extra).

    LSD radix passes over the top ``RADIX_BITS``-bit digits of ``key - min`` only: enough digits to spread
    ``n`` keys over about 4 n buckets (at most the key range's own bit length). If bits remain below those
    digits, ``_fix_runs`` orders each run of equal top bits by the full key (runs are short unless many keys
    share their top bits).
    """
    n = keys.shape[0]
    lo_key = keys.min()
    span = keys.max() - lo_key
    span_bits = _bit_length(span)
    wanted = max(_MIN_TOP_BITS, _bit_length(np.uint64(n)) + 2)
    passes = (min(span_bits, wanted) + RADIX_BITS - 1) // RADIX_BITS
    drop = max(0, span_bits - passes * RADIX_BITS)
    k_a = np.empty(n, np.uint64)
    for j in prange(n):
        k_a[j] = keys[j] - lo_key
    v_a = vals.copy()
    e_a = extra.copy()
    k_b = np.empty(n, np.uint64)
    v_b = np.empty_like(vals)
    e_b = np.empty_like(extra)
    size = (n + num_chunks - 1) // num_chunks
    hist = np.empty((num_chunks, _RADIX), np.int64)
    for pas in range(passes):
        shift = np.uint64(drop + pas * RADIX_BITS)
        for c in prange(num_chunks):
            _digit_histogram(k_a, c * size, min(n, (c + 1) * size), shift, hist[c])
        total = 0
        for d in range(_RADIX):
            for c in range(num_chunks):
                cnt = hist[c, d]
                hist[c, d] = total
                total += cnt
        for c in prange(num_chunks):
            _digit_scatter(k_a, v_a, e_a, c * size, min(n, (c + 1) * size), shift, hist[c], k_b, v_b, e_b)
        k_a, k_b = k_b, k_a
        v_a, v_b = v_b, v_a
        e_a, e_b = e_b, e_a
    if drop > 0:
        _fix_runs(k_a, v_a, e_a, drop)
    return v_a, e_a


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
    """CSR offsets [T + 1] and ids [I]; ``counts`` becomes each chunk's write cursor per tile.

    Also the Gaussian-major numbering of the intersections: the intersections of the j-th Gaussian in depth order
    (its tiles in row-major order, so its slots in increasing order) get the ranks ``isect_start[j]`` to
    ``isect_start[j + 1] - 1``; ``slot_rank[p]`` is the rank of slot p.
    """
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
    isect_start = np.empty(m + 1, np.int64)
    for j in prange(m):
        tx0, ty0, tx1, ty1 = _unpack_box(boxes[j])
        isect_start[j + 1] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
    isect_start[0] = 0
    for j in range(m):
        isect_start[j + 1] += isect_start[j]
    ids = np.empty(total, np.int32)
    slot_rank = np.empty(total, np.int64)
    size = (m + num_chunks - 1) // num_chunks
    for c in prange(num_chunks):
        _scatter_chunk(order, boxes, c * size, min(m, (c + 1) * size), tiles_x, counts[c], ids, isect_start, slot_rank)
    return offsets, ids, isect_start, slot_rank


def _num_chunks(n: int) -> int:
    return max(1, min(CHUNKS_PER_THREAD * numba.get_num_threads(), n // 1024 + 1))


def depth_order(idx: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """``idx`` (ascending int64 indices) sorted stably by ``depths[idx]`` (float64), as int64."""
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if idx.shape[0] < 2:
        return idx.copy()
    depth_bits = np.ascontiguousarray(depths, dtype=np.float64).view(np.uint64)
    keys = run_parallel(_depth_keys, idx, depth_bits, chunk=GAUSSIANS_PER_CHUNK)
    order, _ = run_parallel(_radix_sort, keys, idx, np.empty(0, np.uint64), _num_chunks(idx.shape[0]), chunk=0)
    return order


def bin_sorted(idx: np.ndarray, depths: np.ndarray, pixel_box: np.ndarray, tile_size: int, tiles_x: int,
               tiles_y: int):
    """CSR tile lists of the Gaussians ``idx`` (ascending), each tile's list by increasing depth (ties: index).

    Every Gaussian goes to every tile its inclusive pixel box ``(u0, v0, u1, v1)`` touches. The packed tile boxes
    ride along in the depth sort, so no step reads ``pixel_box`` in depth (random) order.
    Returns (offsets [T + 1] int64, ids [I] int32, order [M] int64 (the Gaussians by depth), isect_start [M + 1]
    int64, slot_rank [I] int64): slot p is intersection number ``slot_rank[p]`` in Gaussian-major order, where
    ``order[j]`` owns the numbers ``isect_start[j]`` to ``isect_start[j + 1] - 1`` (in increasing slot order).
    The blending backward writes its per-intersection gradients at those numbers and sums them per Gaussian
    with sequential reads.
    """
    num_tiles = tiles_x * tiles_y
    if max(tiles_x, tiles_y) > MAX_TILES_PER_SIDE:
        raise ValueError(f"bin_sorted: at most {MAX_TILES_PER_SIDE} tiles per side, got {tiles_x} x {tiles_y}")
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if idx.shape[0] == 0:
        return (np.zeros(num_tiles + 1, np.int64), np.zeros(0, np.int32), idx, np.zeros(1, np.int64),
                np.zeros(0, np.int64))
    pixel_box = np.ascontiguousarray(pixel_box, dtype=np.int64)
    boxes = run_parallel(_tile_boxes, idx, pixel_box, tile_size, chunk=GAUSSIANS_PER_CHUNK)
    if idx.shape[0] > 1:
        depth_bits = np.ascontiguousarray(depths, dtype=np.float64).view(np.uint64)
        keys = run_parallel(_depth_keys, idx, depth_bits, chunk=GAUSSIANS_PER_CHUNK)
        idx, boxes = run_parallel(_radix_sort, keys, idx, boxes, _num_chunks(idx.shape[0]), chunk=0)
    chunks = _num_chunks(idx.shape[0])
    counts = run_parallel(_count_tiles, boxes, tiles_x, num_tiles, chunks, chunk=0)
    offsets, ids, isect_start, slot_rank = run_parallel(_scatter_tiles, idx, boxes, counts, tiles_x, num_tiles,
                                                        chunk=0)
    return offsets, ids, idx, isect_start, slot_rank
