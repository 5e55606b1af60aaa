"""SegGaussian: build labelled 3D Gaussian Splatting datasets (SegGaussian) on the CPU."""
import os as _os

__version__ = "0.1.0"

# numba's parallel kernels (rasterizer, sparse conv) use the OpenMP layer; naming it skips the probe of an
# older system TBB, which only prints a warning. A user's own setting wins.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
