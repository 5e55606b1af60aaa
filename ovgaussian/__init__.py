"""OVGaussian: open-vocabulary segmentation of 3D Gaussian scenes (model, trainer, benchmark)."""
import os as _os

__version__ = "0.1.0"

# As in seggaussian: numba's parallel kernels use the OpenMP layer (skips a warning-only probe of TBB).
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
