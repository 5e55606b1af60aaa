"""Optional CUDA backend through gsplat (used only when ``backend="gsplat"`` is asked for explicitly).

gsplat's "classic" mode follows the same 3DGS reference rules (0.3 px dilation, ALPHA_MAX clamp with
zero gradient, ALPHA_MIN, TRANSMITTANCE_MIN), but it has no per-pixel 3-sigma cutoff and it uses its
own off-screen Jacobian clamp: images agree with the CPU backends up to faint Gaussian tails.
"""

from __future__ import annotations

import torch
from torch import Tensor

from seggaussian.core.constants import COV2D_DILATION, FAR_PLANE, NEAR_PLANE, TILE_SIZE


class GsplatUnavailable(RuntimeError):
    """gsplat or CUDA is missing."""


def gsplat_available() -> tuple[bool, str]:
    """(available, reason when not)."""
    if not torch.cuda.is_available():
        return False, "the gsplat backend needs CUDA, and torch.cuda.is_available() is False"
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False, "the gsplat backend needs the gsplat package (pip install gsplat)"
    return True, ""


def rasterize_gsplat(
    means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, viewmat: Tensor, K: Tensor,
    width: int, height: int, colors_or_sh: Tensor, sh_degree: int | None, background: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor]:  # image [H, W, D], alpha [H, W], expected depth [H, W]
    ok, reason = gsplat_available()
    if not ok:
        raise GsplatUnavailable(reason)
    from gsplat import rasterization

    device = torch.device("cuda")
    dtype = means.dtype
    to = lambda x: x.to(device=device, dtype=torch.float32)  # noqa: E731
    colors, alphas, _meta = rasterization(
        to(means), to(quats), torch.exp(to(log_scales)), torch.sigmoid(to(opacity_logits)), to(colors_or_sh),
        to(viewmat)[None], to(K)[None], int(width), int(height), near_plane=NEAR_PLANE, far_plane=FAR_PLANE,
        eps2d=COV2D_DILATION, sh_degree=sh_degree, tile_size=TILE_SIZE, render_mode="RGB+ED",
        rasterize_mode="classic", backgrounds=None,
    )
    image, depth, alpha = colors[0, ..., :-1], colors[0, ..., -1], alphas[0, ..., 0]
    if background is not None:
        image = image + (1.0 - alpha)[..., None] * to(background)
    back = lambda x: x.to(device=means.device, dtype=dtype)  # noqa: E731
    return back(image), back(alpha), back(depth)
