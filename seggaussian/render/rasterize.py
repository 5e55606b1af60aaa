"""One entry point for rendering Gaussians: projection -> colours -> front-to-back blending.

``rasterize`` picks a blending backend (``fast``: numba tile kernels; ``reference``: per-pixel torch;
``torch``: torch vectorized over tiles, for benchmarks) behind the same projection, so every backend
culls, orders and cuts off exactly the same Gaussians.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from torch import Tensor

from seggaussian.render.projection import Projection, project_gaussians
from seggaussian.render.sh import sh_to_colors

if TYPE_CHECKING:
    from seggaussian.cameras import Camera
    from seggaussian.gaussians import Gaussians

BACKENDS = ("auto", "fast", "reference", "torch", "gsplat")
#: Accumulated alpha below this counts as empty when normalizing the expected depth (any blended
#: Gaussian contributes at least ALPHA_MIN, so this only separates exactly-empty pixels).
DEPTH_ALPHA_EPS = 1e-12


class RenderOutput(NamedTuple):
    """A rendered view.

    Fields:
        image: ``[H, W, D]`` blended colours/features plus ``(1 - alpha) * background``.
        alpha: ``[H, W]`` accumulated opacity ``1 - T``.
        depth: ``[H, W]`` expected camera depth of the blended Gaussians, ``sum w z / alpha`` (0 where
            nothing was blended).
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor


def _check_finite(name: str, x: Tensor | None, allow_inf: bool = False) -> None:
    """ValueError naming ``name`` when ``x`` holds NaN (or Inf unless ``allow_inf``).

    Checked with numpy on a zero-copy view: single-threaded, so it costs no torch thread synchronization.
    """
    if x is None or x.numel() == 0:
        return
    values = x.detach().cpu().numpy()
    bad = np.isnan(values) if allow_inf else ~np.isfinite(values)
    if bad.any():
        kind = "NaN" if allow_inf else "NaN/Inf"
        raise ValueError(f"rasterize: {name} holds {kind} ({int(bad.sum())} values)")


def check_inputs(means, quats, log_scales, opacity_logits, viewmat, K, width, height) -> int:
    """Validate shapes and values; returns N. ``log_scales`` and ``opacity_logits`` may be +-inf."""
    n = means.shape[0] if means.ndim == 2 else -1
    for name, x, shape in (
        ("means", means, (n, 3)), ("quats", quats, (n, 4)), ("log_scales", log_scales, (n, 3)),
        ("opacity_logits", opacity_logits, (n,)), ("viewmat", viewmat, (4, 4)), ("K", K, (3, 3)),
    ):
        if tuple(x.shape) != shape or n < 0:
            raise ValueError(f"rasterize: {name} has shape {tuple(x.shape)}, expected {shape}")
    for name, x in (("means", means), ("quats", quats), ("viewmat", viewmat), ("K", K)):
        _check_finite(name, x)
    _check_finite("log_scales", log_scales, allow_inf=True)
    _check_finite("opacity_logits", opacity_logits, allow_inf=True)
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"rasterize: image size must be positive, got {width}x{height}")
    return n


def resolve_colors(
    n: int, projection: Projection, features: Tensor | None, sh: Tensor | None, sh_degree: int | None,
    dtype: torch.dtype,
) -> Tensor:  # [N, D]
    if features is not None and sh is not None:
        raise ValueError("rasterize: give either features or sh, not both")
    if features is not None:
        if features.ndim != 2 or features.shape[0] != n:
            raise ValueError(f"rasterize: features has shape {tuple(features.shape)}, expected ({n}, D)")
        _check_finite("features", features)
        return features
    if sh is not None:
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"rasterize: sh has shape {tuple(sh.shape)}, expected ({n}, K, 3)")
        _check_finite("sh", sh)
        return sh_to_colors(sh, projection.view_dirs, sh_degree)
    return torch.zeros(n, 0, dtype=dtype)


def default_backend() -> str:
    """``fast`` when the numba kernels import, else ``reference``."""
    try:
        import seggaussian.render.fast  # noqa: F401
        import seggaussian.render.fast_projection  # noqa: F401
    except ImportError:
        return "reference"
    return "fast"


def blend(
    backend: str, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, projection: Projection,
    width: int, height: int,
) -> tuple[Tensor, Tensor]:
    """Dispatch the blending stage: (accumulated colours [H, W, D], accumulated alpha [H, W])."""
    if backend == "reference":
        from seggaussian.render.reference import blend_reference

        return blend_reference(means2d, conics, opacities, colors, projection.depths, projection.valid, width, height)
    from seggaussian.render.tiles import bin_gaussians

    bins = bin_gaussians(projection, width, height, opacities)
    if backend == "torch":
        from seggaussian.render.torch_tiles import blend_torch_tiles

        return blend_torch_tiles(means2d, conics, opacities, colors, bins)
    from seggaussian.render.fast import blend_fast

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
    sh: Tensor | None = None,  # [N, K, 3]
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
        from seggaussian.render.fast_projection import project_gaussians_fast

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
    from seggaussian.render.gsplat_backend import rasterize_gsplat
    from seggaussian.render.sh import sh_degree_of

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
