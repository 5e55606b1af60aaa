"""The OVGaussian network (``network``: voxelized Gaussians -> sparse U-Net -> adapter -> S) and its configuration
(``config``, data only).
"""

__all__ = ["config", "network"]
