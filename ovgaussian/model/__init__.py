"""The OVGaussian network (``network``: voxelized Gaussians -> sparse U-Net -> adapter -> S), its configuration
(``config``, data only) and the adapter's attention over attribute tokens (``token_attention``, a numba row loop).
"""

__all__ = ["config", "network", "token_attention"]
