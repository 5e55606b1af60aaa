"""One entry point for rendering Gaussians: projection -> colours -> front-to-back blending.

``rasterize`` picks a blending backend (``fast``: numba tile kernels; ``reference``: per-pixel torch;
``torch``: torch vectorized over tiles, for benchmarks) behind the same projection, so every backend
culls, orders and cuts off exactly the same Gaussians.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from seggaussian.render.gsplat_backend import rasterize_gsplat
from seggaussian.render.inputs import check_finite, check_inputs
from seggaussian.render.projection import Projection, project_gaussians
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.rasterize_numba import blend_fast
from seggaussian.render.reference import blend_reference
from seggaussian.render.results import RenderOutput
from seggaussian.render.sh import sh_degree_of, sh_to_colors
from seggaussian.render.tiles import bin_gaussians
from seggaussian.render.torch_tiles import blend_torch_tiles

if TYPE_CHECKING:
    from seggaussian.core.cameras import Camera
    from seggaussian.core.gaussians import Gaussians

BACKENDS = ("auto", "fast", "reference", "torch", "gsplat")
#: Accumulated alpha below this counts as empty when normalizing the expected depth (any blended
#: Gaussian contributes at least ALPHA_MIN, so this only separates exactly-empty pixels).
DEPTH_ALPHA_EPS = 1e-12


def resolve_colors(
    n: int, projection: Projection, features: Tensor | None, sh: Tensor | None, sh_degree: int | None,
    dtype: torch.dtype,
) -> Tensor:  # [N, D]
    if features is not None and sh is not None:
        raise ValueError("rasterize: give either features or sh, not both")
    if features is not None:
        if features.ndim != 2 or features.shape[0] != n:
            raise ValueError(f"rasterize: features has shape {tuple(features.shape)}, expected ({n}, D)")
        check_finite("features", features)
        return features
    if sh is not None:
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"rasterize: sh has shape {tuple(sh.shape)}, expected ({n}, num_sh_coeffs, 3)")
        check_finite("sh", sh)
        return sh_to_colors(sh, projection.view_dirs, sh_degree)
    return torch.zeros(n, 0, dtype=dtype)


def default_backend() -> str:
    """The backend ``auto`` resolves to: the numba kernels (numba is a required dependency)."""
    return "fast"


def blend(
    backend: str, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, projection: Projection,
    width: int, height: int,
) -> tuple[Tensor, Tensor]:
    """Dispatch the blending stage: (accumulated colours [H, W, D], accumulated alpha [H, W])."""
    if backend == "reference":
        return blend_reference(means2d, conics, opacities, colors, projection.depths, projection.valid, width, height)
    bins = bin_gaussians(projection, width, height, opacities)
    if backend == "torch":
        return blend_torch_tiles(means2d, conics, opacities, colors, bins)
    return blend_fast(means2d, conics, opacities, colors, bins)


def rasterize(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] (w, x, y, z), any norm
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] world-to-camera (OpenCV)
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    features: Tensor | None = None,  # [N, D]
    sh: Tensor | None = None,  # [N, num_sh_coeffs, 3]
    sh_degree: int | None = None,
    background: Tensor | None = None,  # [D]
    backend: str = "auto",
) -> RenderOutput:
    """Render N Gaussians into an ``height x width`` image of D channels (3DGS reference semantics).

    Colours come from ``features`` (used as given) or from ``sh`` evaluated per Gaussian along the view
    direction camera centre -> mean, ``max(SH + 0.5, 0)``, using bands up to ``sh_degree``. The result is
    differentiable in means, quats, log_scales, opacity_logits and features / sh. Output dtype is the
    dtype of ``means`` (the fast backend blends in float32). See ``reference.py`` for the blending rule
    and the gradient convention at the ALPHA_MAX clamp.
    """
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")
    width, height = int(width), int(height)
    n = check_inputs(means, quats, log_scales, opacity_logits, viewmat, K, width, height)
    dtype = means.dtype if means.dtype.is_floating_point else torch.float32
    if backend == "auto":
        backend = default_backend()
    if backend == "gsplat":
        return _rasterize_gsplat(means, quats, log_scales, opacity_logits, viewmat, K, width, height, features, sh,
                                 sh_degree, background)
    if backend == "fast":
        projection = project_gaussians_fast(means, quats, log_scales, viewmat, K, width, height)
    else:
        projection = project_gaussians(means, quats, log_scales, viewmat, K, width, height)
    colors = resolve_colors(n, projection, features, sh, sh_degree, dtype)
    dim = colors.shape[1]
    if background is not None and tuple(background.shape) != (dim,):
        raise ValueError(f"rasterize: background has shape {tuple(background.shape)}, expected ({dim},)")

    blend_dtype = dtype if backend == "reference" else torch.float32
    colors_z = torch.cat([colors.to(blend_dtype), projection.depths.to(blend_dtype)[:, None]], 1)
    opacities = torch.sigmoid(opacity_logits.to(blend_dtype))
    # the fast kernels convert to float32 themselves (and return gradients in the given dtype)
    geometry_dtype = projection.means2d.dtype if backend == "fast" else blend_dtype
    accum, alpha = blend(
        backend, projection.means2d.to(geometry_dtype), projection.conics.to(geometry_dtype), opacities, colors_z,
        projection, width, height,
    )
    accum, alpha = accum.to(dtype), alpha.to(dtype)
    image = accum[..., :dim]
    if background is not None:
        image = image + (1.0 - alpha)[..., None] * background.to(dtype)
    depth_sum = accum[..., dim]
    empty = alpha <= DEPTH_ALPHA_EPS
    safe_alpha = torch.where(empty, torch.ones_like(alpha), alpha)
    depth = torch.where(empty, torch.zeros_like(depth_sum), depth_sum / safe_alpha)
    return RenderOutput(image, alpha, depth)


def _rasterize_gsplat(means, quats, log_scales, opacity_logits, viewmat, K, width, height, features, sh, sh_degree,
                      background) -> RenderOutput:
    if (features is None) == (sh is None):
        raise ValueError("rasterize: the gsplat backend needs exactly one of features or sh")
    degree = None if sh is None else (sh_degree_of(sh) if sh_degree is None else int(sh_degree))
    return RenderOutput(*rasterize_gsplat(means, quats, log_scales, opacity_logits, viewmat, K, width, height,
                                          features if sh is None else sh, degree, background))


def camera_tensors(camera: "Camera") -> tuple[Tensor, Tensor]:
    """(viewmat [4, 4], K [3, 3]) of a numpy Camera as float64 torch tensors."""
    return torch.as_tensor(camera.viewmat, dtype=torch.float64), torch.as_tensor(camera.K, dtype=torch.float64)


def render_gaussians(
    gaussians: "Gaussians",
    camera: "Camera",
    *,
    features: Tensor | None = None,
    sh_degree: int | None = None,
    background: Tensor | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """Render numpy ``Gaussians`` from a numpy ``Camera``: SH colours unless ``features`` are given."""
    t = gaussians.to_torch()
    viewmat, K = camera_tensors(camera)
    return rasterize(
        t["means"], t["quats"], t["log_scales"], t["opacity_logits"], viewmat, K, camera.width, camera.height,
        features=features, sh=None if features is not None else t["sh"], sh_degree=sh_degree,
        background=background, backend=backend,
    )
