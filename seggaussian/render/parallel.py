"""How the render package's parallel numba kernels are called: work chunk sizes and :func:`run_parallel`.

Every kernel with a ``prange`` loop (blending, projection, binning, SH colours, pixel blend weights) is called
through :func:`run_parallel`, which sets numba's work chunk for the call and restores torch's thread count,
which numba's first parallel call may reset.
"""

from __future__ import annotations

import numba
import torch

#: Tiles handed to a thread at a time (tiles differ widely in work; small chunks balance the load).
TILES_PER_CHUNK = 2
#: Gaussians handed to a thread at a time in per-Gaussian loops (uniform work: large chunks).
GAUSSIANS_PER_CHUNK = 4096


def run_parallel(kernel, *args, chunk: int = TILES_PER_CHUNK):
    """Call a parallel numba kernel with a work chunk of ``chunk`` iterations (0: numba's default), keeping
    torch's thread count unchanged."""
    threads = torch.get_num_threads()
    with numba.parallel_chunksize(chunk):
        result = kernel(*args)
    if torch.get_num_threads() != threads:  # numba's OpenMP layer may reset torch's thread count
        torch.set_num_threads(threads)
    return result
