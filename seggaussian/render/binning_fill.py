"""The former binning, kept as the reference of ``binning_numba`` and the benchmark's "before": after a stable argsort
by depth (``tiles.bin_gaussians_argsort``), every tile's list is filled by bands of tile rows, each band owned by one
thread (no races; each tile receives its Gaussians in the given order, as a serial fill would). Whole pixel boxes, no
ellipse cull."""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from seggaussian.core.constants import TILE_SIZE
from seggaussian.render.parallel import GAUSSIANS_PER_CHUNK, run_parallel

_JIT = dict(cache=True, nogil=True)

#: Bands of tile rows per thread (a few, for load balance).
BANDS_PER_THREAD = 2


@numba.njit(parallel=True, **_JIT)
def _gather_tile_boxes(order, pixel_box, tile_size):
    """Tile boxes of the Gaussians in ``order`` (one random read per Gaussian, in parallel)."""
    boxes = np.empty((order.shape[0], 4), np.int32)
    for j in prange(order.shape[0]):
        g = order[j]
        for k in range(4):
            boxes[j, k] = pixel_box[g, k] // tile_size
    return boxes


@numba.njit(parallel=True, **_JIT)
def _fill_sorted(order, boxes, tiles_x, tiles_y, num_bands):
    """Counting sort into tiles, parallel over bands of tile rows (each band owns its tiles: no races,
    and every tile receives its Gaussians in ``order``, as a serial fill would)."""
    num_tiles = tiles_x * tiles_y
    band_rows = (tiles_y + num_bands - 1) // num_bands
    counts = np.zeros(num_tiles + 1, np.int64)
    for band in prange(num_bands):
        r0 = band * band_rows
        r1 = min(tiles_y, r0 + band_rows) - 1
        for j in range(order.shape[0]):
            for ty in range(max(boxes[j, 1], r0), min(boxes[j, 3], r1) + 1):
                for tx in range(boxes[j, 0], boxes[j, 2] + 1):
                    counts[ty * tiles_x + tx + 1] += 1
    for t in range(num_tiles):
        counts[t + 1] += counts[t]
    cursor = counts[:-1].copy()
    ids = np.empty(counts[num_tiles], np.int32)
    for band in prange(num_bands):
        r0 = band * band_rows
        r1 = min(tiles_y, r0 + band_rows) - 1
        for j in range(order.shape[0]):
            g = order[j]
            for ty in range(max(boxes[j, 1], r0), min(boxes[j, 3], r1) + 1):
                for tx in range(boxes[j, 0], boxes[j, 2] + 1):
                    t = ty * tiles_x + tx
                    ids[cursor[t]] = g
                    cursor[t] += 1
    return counts, ids


def fill_tile_lists(order: np.ndarray, pixel_box: np.ndarray, tiles_x: int, tiles_y: int):
    """CSR tile lists: Gaussians visited in ``order`` (front to back) appended to every tile their
    inclusive pixel box ``(u0, v0, u1, v1)`` touches. Returns (offsets [T + 1] int64, ids [I] int32)."""
    boxes = run_parallel(_gather_tile_boxes, order, pixel_box, TILE_SIZE, chunk=GAUSSIANS_PER_CHUNK)
    num_bands = min(tiles_y, BANDS_PER_THREAD * numba.get_num_threads())
    return run_parallel(_fill_sorted, order, boxes, tiles_x, tiles_y, num_bands, chunk=1)
