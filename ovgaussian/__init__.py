"""OVGaussian: open-vocabulary segmentation of 3D Gaussian scenes (model, trainer, benchmark)."""
# The dataset package sets the process-wide threading defaults (numba's OpenMP layer, passive OpenMP waits)
# before torch or numba load; importing it first gives every ovgaussian command the same ones.
import seggaussian as _seggaussian  # noqa: F401  (imported for its environment defaults)

__version__ = "0.1.0"
