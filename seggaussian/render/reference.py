"""The obviously-correct rasterizer: every pixel walks all Gaussians front to back (pure torch).

Slow (one Python step per Gaussian, all pixels at once), differentiable by autograd, used by the tests
as the ground truth for the fast kernels. The blending rule, written once here and mirrored by the
kernels in ``fast.py``:

    for each Gaussian in increasing depth (ties: lower index first), at pixel centre p = (u+.5, v+.5):
        d = p - mean2d;  s = a dx^2 + 2 b dx dy + c dy^2          (Mahalanobis^2, conic (a, b, c))
        skip unless s <= RADIUS_SIGMAS^2                           (3-sigma cutoff, per pixel)
        alpha = min(ALPHA_MAX, opacity * exp(-s / 2))
        skip if alpha < ALPHA_MIN
        if T * (1 - alpha) < TRANSMITTANCE_MIN: stop this pixel (this Gaussian is not blended)
        out += colour * alpha * T;  T *= 1 - alpha
    accumulated alpha = 1 - T

The per-pixel 3-sigma cutoff is this toolkit's choice: the 3DGS CUDA code cuts at the granularity of
the tiles touched by its 3-sigma box. Cutting per pixel makes the image independent of tiling and
binning (so the reference needs no tiles at all); the dropped tails have alpha <= opacity * exp(-4.5).

Gradient convention at the ALPHA_MAX clamp (gsplat's): where opacity * G > ALPHA_MAX the alpha is the
constant ALPHA_MAX, so no gradient reaches the opacity or the 2D Gaussian through that pixel (the pixel
still passes gradients to the colour). ``torch.clamp`` gives exactly this; the fast kernels match it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from seggaussian.core.constants import ALPHA_MAX, ALPHA_MIN, RADIUS_SIGMAS, TRANSMITTANCE_MIN


def depth_order(depths: Tensor, valid: Tensor) -> Tensor:  # -> [M] int64 indices of valid Gaussians
    """Valid Gaussians sorted front to back; equal depths keep index order (stable)."""
    idx = torch.nonzero(valid, as_tuple=False).reshape(-1)
    order = torch.sort(depths.detach()[idx], stable=True).indices
    return idx[order]


def blend_reference(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D]
    depths: Tensor,  # [N] (ordering only)
    valid: Tensor,  # [N] bool
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:  # accumulated colours [H, W, D], accumulated alpha [H, W]
    """Front-to-back alpha blending, pixel by pixel (vectorized over pixels only)."""
    dtype = colors.dtype
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij"
    )
    px, py = (u.reshape(-1) + 0.5), (v.reshape(-1) + 0.5)
    num_pixels, dim = px.shape[0], colors.shape[1]
    transmittance = torch.ones(num_pixels, dtype=dtype)
    accum = torch.zeros(num_pixels, dim, dtype=dtype)
    done = torch.zeros(num_pixels, dtype=torch.bool)
    means2d, conics, opacities = means2d.to(dtype), conics.to(dtype), opacities.to(dtype)
    for g in depth_order(depths, valid).tolist():
        dx, dy = px - means2d[g, 0], py - means2d[g, 1]
        a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
        s = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
        inside = s <= RADIUS_SIGMAS**2
        alpha = torch.clamp(opacities[g] * torch.exp(-0.5 * s.clamp_min(0.0)), max=ALPHA_MAX)
        use = inside & (alpha >= ALPHA_MIN) & ~done
        test_t = transmittance * (1.0 - alpha)
        stop = use & (test_t < TRANSMITTANCE_MIN)
        use = use & ~stop
        done = done | stop
        weight = torch.where(use, alpha * transmittance, torch.zeros_like(alpha))
        accum = accum + weight[:, None] * colors[g]
        transmittance = torch.where(use, test_t, transmittance)
    # keep the outputs in the graph when nothing was blended (backward then gives zero gradients)
    anchor = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + colors.sum())
    accum, transmittance = accum + anchor, transmittance + anchor
    return accum.reshape(height, width, dim), (1.0 - transmittance).reshape(height, width)
