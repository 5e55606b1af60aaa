"""SegGaussian: build labelled 3D Gaussian Splatting datasets (SegGaussian) on the CPU."""
__version__ = "0.1.0"
