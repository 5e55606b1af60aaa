"""Thread caps of one worker process: torch's intra-op threads and numba's parallel kernels, set together.

A process that shares the cores with other workers must cap both: the fit's rasterizer and the sparse convolution
run numba parallel kernels, and two workers with two numba threads each on two cores wait at every kernel's
barrier for a descheduled thread (the profile's fits took about 75 s wall each, two at a time, at 60 % CPU per
worker; BENCHMARKS.md "Fitted splats").
"""

from __future__ import annotations

import numba
import torch


def cap_threads(threads: int) -> None:
    """Let torch and numba use at most ``threads`` threads (at least 1; numba never above its configured pool)."""
    threads = max(1, int(threads))
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
