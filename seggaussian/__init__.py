"""SegGaussian: build labelled 3D Gaussian Splatting datasets (SegGaussian) on the CPU."""
import os as _os

__version__ = "0.1.0"

# numba's parallel kernels (rasterizer, sparse conv) use the OpenMP layer; naming it skips the probe of an
# older system TBB, which only prints a warning. A user's own setting wins.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
# OpenMP threads (torch's and numba's) sleep while they wait instead of spinning. On the 2-core machines
# libgomp's default spin burnt 3-4x the CPU of a training step whenever another process shared the cores
# (paper-scale step: 83.5 -> 22.8 s CPU; one bench-suite epoch: 143.5 -> 38.2 s CPU; benchmarks/results/paper_scale.md,
# bench_suite.md).
# It only takes effect when this package is imported before torch starts its thread pool, as every
# `seggaussian` / `ovgaussian` command does. A user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# glibc keeps freed memory for reuse instead of unmapping it: arrays of a million Gaussians otherwise start on fresh
# pages each time, at about 1 ms per MB of page faults (seggaussian/util/allocator.py). SEGGAUSSIAN_MALLOC=system
# opts out.
from seggaussian.util.allocator import keep_freed_memory as _keep_freed_memory  # noqa: E402

_keep_freed_memory()

# numba's kernel cache in a folder named by the digest of every numba module's source, so an update never
# runs a stale cached kernel (numba checks only the jitted function's own file; seggaussian/util/numba_cache.py).
if "NUMBA_CACHE_DIR" not in _os.environ:
    from seggaussian.util.numba_cache import default_numba_cache_dir as _default_numba_cache_dir

    _folder = _default_numba_cache_dir()
    if _folder is not None:
        _os.environ["NUMBA_CACHE_DIR"] = _folder
