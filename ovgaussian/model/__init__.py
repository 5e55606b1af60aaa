"""The OVGaussian network (``network``: voxelized Gaussians -> sparse U-Net -> adapter -> S), its configuration
(``config``, data only), the adapter's attention over attribute tokens (``token_attention``, a numba row loop), a
linear layer for few input columns (``narrow_linear``) and the adapter's MLP with fused bias + ReLU passes
(``relu_mlp``), and where the network places a splat's Gaussians (``surface``: on the splat's own surface).
"""

__all__ = ["config", "narrow_linear", "network", "relu_mlp", "surface", "token_attention"]
