"""Per-pixel blend weights W (front-most contributors) and renders that reuse them: M = W S.

For fixed geometry the rendered feature of a pixel is linear in the per-Gaussian features,
``M[p] = sum_k weights[p, k] * features[ids[p, k]]``, so a view's weights are computed once and reused
for any feature (semantic vectors, labels) without re-rasterizing.
"""

from __future__ import annotations

import torch
from torch import Tensor

from seggaussian.core.constants import ALPHA_MAX, ALPHA_MIN, RADIUS_SIGMAS, TRANSMITTANCE_MIN
from seggaussian.render.inputs import check_inputs
from seggaussian.render.projection import project_gaussians
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.rasterize_numba import blend_weights_fast
from seggaussian.render.reference import depth_order
from seggaussian.render.results import BlendWeights
from seggaussian.render.tiles import bin_gaussians

#: Default number of contributors kept per pixel. Past ~16 front-most Gaussians the remaining
#: transmittance of a converged 3DGS scene is small; ``residual_alpha`` reports what was left out.
DEFAULT_TOP_K = 16


def blend_weights_reference(
    means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, valid: Tensor,
    width: int, height: int, top_k: int,
) -> BlendWeights:
    """Same walk as ``reference.blend_reference`` (float32), recording the first ``top_k`` weights."""
    dtype = torch.float32
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    px, py = u.reshape(-1) + 0.5, v.reshape(-1) + 0.5
    num_pixels = px.shape[0]
    transmittance = torch.ones(num_pixels, dtype=dtype)
    done = torch.zeros(num_pixels, dtype=torch.bool)
    count = torch.zeros(num_pixels, dtype=torch.int64)
    ids = torch.full((num_pixels, top_k), -1, dtype=torch.int64)
    weights = torch.zeros(num_pixels, top_k, dtype=dtype)
    residual = torch.zeros(num_pixels, dtype=dtype)
    means2d, conics, opacities = means2d.to(dtype), conics.to(dtype), opacities.to(dtype)
    for g in depth_order(depths, valid).tolist():
        dx, dy = px - means2d[g, 0], py - means2d[g, 1]
        s = conics[g, 0] * dx * dx + 2.0 * conics[g, 1] * dx * dy + conics[g, 2] * dy * dy
        alpha = torch.clamp(opacities[g] * torch.exp(-0.5 * s.clamp_min(0.0)), max=ALPHA_MAX)
        use = (s <= RADIUS_SIGMAS**2) & (alpha >= ALPHA_MIN) & ~done
        test_t = transmittance * (1.0 - alpha)
        stop = use & (test_t < TRANSMITTANCE_MIN)
        use = use & ~stop
        done = done | stop
        weight = alpha * transmittance
        keep = use & (count < top_k)
        rows = torch.nonzero(keep).reshape(-1)
        ids[rows, count[rows]] = g
        weights[rows, count[rows]] = weight[rows]
        residual = residual + torch.where(use & ~keep, weight, torch.zeros_like(weight))
        count = count + keep.long()
        transmittance = torch.where(use, test_t, transmittance)
    return BlendWeights(ids.reshape(height, width, top_k), weights.reshape(height, width, top_k),
                        residual.reshape(height, width))


def compute_blend_weights(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    top_k: int = DEFAULT_TOP_K,
    *,
    backend: str = "auto",
) -> BlendWeights:
    """The ``top_k`` front-most contributors per pixel and their weights (no gradient).

    ``render_features(blend, f)`` equals ``rasterize(..., features=f).image`` exactly when ``top_k`` covers
    every contributor (``residual_alpha == 0``); otherwise it misses ``residual_alpha`` worth of weight.
    """
    if int(top_k) < 1:
        raise ValueError(f"compute_blend_weights: top_k must be >= 1, got {top_k}")
    width, height, top_k = int(width), int(height), int(top_k)
    with torch.no_grad():
        check_inputs(means, quats, log_scales, opacity_logits, viewmat, K, width, height)
        if backend == "auto":
            backend = "fast"
        if backend not in ("fast", "reference"):
            raise ValueError(f"compute_blend_weights: backend must be auto, fast or reference, got {backend!r}")
        opacities = torch.sigmoid(opacity_logits.to(torch.float32))
        if backend == "reference":
            projection = project_gaussians(means, quats, log_scales, viewmat, K, width, height)
            return blend_weights_reference(
                projection.means2d.float(), projection.conics.float(), opacities, projection.depths, projection.valid,
                width, height, top_k,
            )
        projection = project_gaussians_fast(means, quats, log_scales, viewmat, K, width, height)
        means2d, conics = projection.means2d.float(), projection.conics.float()

        bins = bin_gaussians(projection, width, height, opacities)
        return blend_weights_fast(means2d, conics, opacities, bins, top_k)


def _slot_inputs(blend: BlendWeights, features: Tensor) -> tuple[Tensor, Tensor]:
    """``(safe_ids, w)`` [H, W, K] of ``render_features``: ids with -1 read as row 0, weights zero in unused slots (in
    ``features``' dtype), after checking ``features`` against the ids."""
    if features.ndim != 2:
        raise ValueError(f"render_features: features has shape {tuple(features.shape)}, expected (N, D)")
    ids = blend.ids
    used = ids >= 0
    if bool(used.any()) and int(ids.max()) >= features.shape[0]:
        raise ValueError(
            f"render_features: blend weights refer to Gaussian {int(ids.max())} "
            f"but features has {features.shape[0]} rows"
        )
    return ids.clamp_min(0), (blend.weights * used).to(features.dtype)


def _slot_sum(safe_ids: Tensor, w: Tensor, features: Tensor) -> Tensor:  # [H, W, K], [H, W, K], [N, D] -> [H, W, D]
    """``sum_k w[..., k] features[safe_ids[..., k]]``, slot by slot (one [H, W, D] gather per slot keeps memory at
    O(H W D))."""
    out = torch.zeros(*safe_ids.shape[:2], features.shape[1], dtype=features.dtype, device=features.device)
    for k in range(safe_ids.shape[2]):
        out = out + w[..., k, None] * features[safe_ids[..., k]]
    return out


class _RenderFeatures(torch.autograd.Function):
    """``M = W S`` with the gradient of ``S`` accumulated into one ``[N, D]`` buffer (``index_add_`` per slot).

    Autograd through :func:`_slot_sum` gives each slot's gather its own zero-filled ``[N, D]`` gradient (K of them:
    16 x 64 MB per million Gaussians with 16-wide features) and then sums them. The forward is the same slot loop.
    """

    @staticmethod
    def forward(ctx, features: Tensor, safe_ids: Tensor, w: Tensor) -> Tensor:
        ctx.save_for_backward(safe_ids, w)
        ctx.num_rows = features.shape[0]
        return _slot_sum(safe_ids, w, features)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        safe_ids, w = ctx.saved_tensors
        dim = grad_out.shape[-1]
        flat = grad_out.reshape(-1, dim)
        grad = torch.zeros(ctx.num_rows, dim, dtype=grad_out.dtype, device=grad_out.device)
        for k in range(safe_ids.shape[2]):
            grad.index_add_(0, safe_ids[..., k].reshape(-1), w[..., k].reshape(-1, 1) * flat)
        return grad, None, None


def render_features(
    blend: BlendWeights,
    features: Tensor,  # [N, D]
) -> Tensor:  # [H, W, D]
    """``M = W S``: blend per-Gaussian features with fixed weights; exact, differentiable in ``features`` (and in
    ``blend.weights`` through autograd's own gathers, as :func:`render_features_reference`, when those require a
    gradient)."""
    safe_ids, w = _slot_inputs(blend, features)
    if blend.weights.requires_grad:
        return _slot_sum(safe_ids, w, features)
    return _RenderFeatures.apply(features, safe_ids, w)


def render_features_reference(blend: BlendWeights, features: Tensor) -> Tensor:  # [H, W, D]
    """:func:`render_features` through autograd's own gathers: the reference its gradient is tested against."""
    return _slot_sum(*_slot_inputs(blend, features), features)
