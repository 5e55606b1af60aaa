"""Recycled int32 arrays for the tile lists of large renders (one concept: reuse without page faults).

A fresh 44 MB array (the tile lists of 1,000,000 Gaussians at 876x584) costs its page faults on first write, about
as long as filling it: 51-72 ms against 31-38 ms into a reused one (BENCHMARKS.md, "Session 9: binning, and the peer benchmark repaired").
"""

from __future__ import annotations

import sys
import threading

import numpy as np

#: Tile lists at least this long come from the recycled buffers.
MIN_POOLED_IDS = 1 << 20
#: At most this many recycled tile-list buffers (a training step renders a few views before its backward).
MAX_POOLED_BUFFERS = 4


class TileIdBuffers:
    """Large tile-list arrays recycled between renders.

    A buffer is handed out again only when nothing else refers to it: every numpy view or slice of it, and every
    tensor made from one, holds a reference to the buffer itself (numpy views point at the array that owns the
    memory), so its reference count is then the pool's own. Lists under :data:`MIN_POOLED_IDS` entries are plain
    ``np.empty`` arrays; at most :data:`MAX_POOLED_BUFFERS` buffers are kept (a render that finds all of them in
    use gets a plain array).
    """

    def __init__(self, max_buffers: int) -> None:
        self._buffers: list[np.ndarray] = []
        self._max_buffers = max_buffers
        self._lock = threading.Lock()

    def _is_free(self, i: int) -> bool:
        # the list's reference and getrefcount's own argument: nobody else holds the buffer
        return sys.getrefcount(self._buffers[i]) <= 2

    def take(self, size: int) -> np.ndarray:
        """An int32 array of ``size`` entries (contents undefined)."""
        if size < MIN_POOLED_IDS:
            return np.empty(size, np.int32)
        with self._lock:
            free = [i for i in range(len(self._buffers)) if self._is_free(i)]
            for i in free:
                if self._buffers[i].shape[0] >= size:
                    return self._buffers[i][:size]
            if free:  # free but too small: replaced by a larger one
                del self._buffers[free[0]]
            elif len(self._buffers) >= self._max_buffers:
                return np.empty(size, np.int32)
            self._buffers.append(np.empty(size + size // 8, np.int32))  # headroom for the next frame's count
            return self._buffers[-1][:size]

    def clear(self) -> None:
        """Forget every buffer (memory still referenced elsewhere stays valid)."""
        with self._lock:
            self._buffers.clear()


#: The process's buffers (``binning_numba.bin_sorted`` takes its tile lists from them).
TILE_ID_BUFFERS = TileIdBuffers(MAX_POOLED_BUFFERS)
