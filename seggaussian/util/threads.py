"""Thread caps of a process: torch's intra-op threads and numba's parallel kernels, set together.

A process that shares the cores with other workers must cap both: the fit's rasterizer and the sparse convolution
run numba parallel kernels, and two workers with two numba threads each on two cores wait at every kernel's
barrier for a descheduled thread (the profile's fits took about 75 s wall each, two at a time, at 60 % CPU per
worker, on the benchmark profile's fits).

Small work gains nothing from several threads: with passive OpenMP waits (``seggaussian/__init__.py``) every
parallel region wakes sleeping threads, and a training step of the demo's size runs thousands of small regions.
:func:`threads_for_gaussians` picks one thread below :data:`PARALLEL_MIN_GAUSSIANS` Gaussians of work
(benchmarks/results/train.md, "Threads and checkpointing").
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import numba
import torch

#: Gaussians per unit of work (a training step's batch, a scene evaluated) below which one thread does it. Measured
#: on the 2-core machines with passive OpenMP waits (benchmarks/results/train.md, "Threads and checkpointing"): a demo step (3 scenes of
#: 15,000 fitted Gaussians, slim network) took 1.4-1.6 s wall with one thread and 2.4-2.7 s with two; 3 x 100,000
#: Gaussians (MinkUNet34C, 5 cm) about 20 s either way; 1 x 1,000,000 18-22 s with one thread and 16-20 s with two.
PARALLEL_MIN_GAUSSIANS = 1_000_000


def cap_threads(threads: int) -> None:
    """Let torch and numba use at most ``threads`` threads (at least 1; numba never above its configured pool)."""
    threads = max(1, int(threads))
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def threads_for_gaussians(gaussians: int, requested: int | None = None) -> int:
    """Threads for work on ``gaussians`` Gaussians: ``requested`` when given, else 1 below
    :data:`PARALLEL_MIN_GAUSSIANS` and torch's current count above it (never more than the current cap)."""
    if requested is not None:
        if requested < 1:
            raise ValueError(f"threads must be at least 1, got {requested}")
        return int(requested)
    return 1 if gaussians < PARALLEL_MIN_GAUSSIANS else torch.get_num_threads()


@contextlib.contextmanager
def thread_cap(threads: int) -> Iterator[int]:
    """:func:`cap_threads` for the block, then torch's and numba's previous counts again; yields ``threads``."""
    torch_before, numba_before = torch.get_num_threads(), numba.get_num_threads()
    cap_threads(threads)
    try:
        yield threads
    finally:
        torch.set_num_threads(torch_before)
        numba.set_num_threads(numba_before)
