"""The OVGaussian network (``network``: voxelized Gaussians -> sparse U-Net -> adapter -> S), its configuration
(``config``, data only), the adapter's attention over attribute tokens (``token_attention``, a numba row loop) and a
linear layer for few input columns (``narrow_linear``).
"""

__all__ = ["config", "narrow_linear", "network", "token_attention"]
