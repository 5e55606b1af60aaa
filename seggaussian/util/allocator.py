"""glibc malloc settings that keep freed memory for reuse instead of returning it to the kernel.

Rendering a million Gaussians, binning them and training on them allocate and free arrays of tens to hundreds of
megabytes, again and again. glibc serves every block above its mmap threshold (at most 32 MB) with a fresh ``mmap``
and unmaps it on ``free``; below it, it trims the top of the heap back to the kernel. Either way the next array of
that size starts on fresh pages, and the kernel zeroes each page on its first write. On these machines that costs
about 1 ms per MB: a 1,000,000-Gaussian projection takes 48-58 ms when its outputs reuse freed memory and 155-175
ms when they land on fresh pages (the previous projection still alive, as in a training step), and the paper-scale
step spent 38 s of system time in page faults (benchmarks/results/train.md, "Page faults").

:func:`keep_freed_memory` sets ``M_MMAP_MAX = 0`` (every block comes from the heap) and ``M_TRIM_THRESHOLD`` to
its largest value (freed memory stays mapped), so freed blocks are reused without faults. The process's resident
size then stays at its peak rather than shrinking after it. glibc still falls back to ``mmap`` where a thread's heap
cannot grow, so no allocation fails for it.

``import seggaussian`` applies it (``seggaussian/__init__.py``), as it sets the OpenMP wait policy. Setting the
environment variable ``SEGGAUSSIAN_MALLOC=system`` before the import keeps glibc's own behaviour. Other C libraries
are left alone.
"""

from __future__ import annotations

import ctypes
import os
import platform

#: Environment variable: ``system`` keeps glibc's defaults; anything else (or unset) applies the settings.
MALLOC_ENV = "SEGGAUSSIAN_MALLOC"
#: mallopt parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
#: Largest value mallopt takes (an int): freed memory at the heap's top is returned only beyond 2 GB.
TRIM_THRESHOLD = 2**31 - 1

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Apply the settings once per process; True when they are in effect (glibc, not opted out)."""
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get(MALLOC_ENV, "").strip().lower() == "system":
        return False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _applied = mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    return _applied


def settings() -> dict:
    """What a benchmark records about the allocator: applied or not, and the opt-out variable's value."""
    return {"keep_freed_memory": bool(_applied), MALLOC_ENV: os.environ.get(MALLOC_ENV)}
