"""How the project's parallel numba kernels are called: work chunk sizes, :func:`run_parallel`, and the helpers of
kernels that sum columns per block of rows or take scalars in their working dtype.

Every kernel with a ``prange`` loop (blending, projection, binning, SH colours, pixel blend weights; the network's
token attention and MLP passes; the Gram-form logits' row passes) is called through :func:`run_parallel`, which sets
numba's work chunk for the call and restores torch's thread count, which numba's first parallel call may reset.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

#: Tiles handed to a thread at a time (tiles differ widely in work; small chunks balance the load).
TILES_PER_CHUNK = 2
#: Gaussians handed to a thread at a time in per-Gaussian loops (uniform work: large chunks).
GAUSSIANS_PER_CHUNK = 4096
#: Rows per block of a kernel's column sums: each block writes one partial row and the partials are added in block
#: order (no atomics: the same result on any thread count).
SUM_BLOCK_ROWS = 1024


def sum_blocks(rows: int) -> int:
    """Blocks of :data:`SUM_BLOCK_ROWS` (at least one) that a column-summing kernel needs for ``rows`` rows."""
    return max(1, -(-rows // SUM_BLOCK_ROWS))


def dtype_scalars(value: float, dtype) -> np.ndarray:
    """``[value]`` in a kernel's working dtype (a Python float would promote float32 work to float64)."""
    return np.array([value], dtype=dtype)


def run_parallel(kernel, *args, chunk: int = TILES_PER_CHUNK):
    """Call a parallel numba kernel with a work chunk of ``chunk`` iterations (0: numba's default), keeping
    torch's thread count unchanged."""
    threads = torch.get_num_threads()
    with numba.parallel_chunksize(chunk):
        result = kernel(*args)
    if torch.get_num_threads() != threads:  # numba's OpenMP layer may reset torch's thread count
        torch.set_num_threads(threads)
    return result
