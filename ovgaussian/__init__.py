"""OVGaussian: open-vocabulary segmentation of 3D Gaussian scenes (model, trainer, benchmark)."""
__version__ = "0.1.0"
