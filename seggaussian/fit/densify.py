"""Adaptive density control of a fit (3DGS): view-space gradient statistics, clone/split/prune, opacity reset.

The view-space gradient is recovered from the gradient of each Gaussian's 3D mean (see ``seggaussian.fit.optimize``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from seggaussian.core.constants import NEAR_PLANE, RADIUS_SIGMAS
from seggaussian.fit.config import FitConfig
from seggaussian.fit.params import PARAMETER_NAMES, GaussianParameters, normalized
from seggaussian.fit.views import ViewData
from seggaussian.core.rotations import quats_to_rotmats_torch

if TYPE_CHECKING:
    import torch

def view_space_stats(means: "torch.Tensor", means_grad: "torch.Tensor", log_scales: "torch.Tensor",
                     view: ViewData) -> tuple["torch.Tensor", "torch.Tensor", "torch.Tensor"]:
    """Per Gaussian in one view: NDC gradient norm of the projected centre ``[N]``, visibility ``[N]``
    (in front of the camera, footprint touching the image) and screen radius in pixels ``[N]``."""
    import torch

    rot = view.viewmat[:3, :3]
    cam = means @ rot.T + view.viewmat[:3, 3]
    z = cam[:, 2]
    fx, fy, cx, cy = view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2]
    w, h = view.camera.width, view.camera.height
    in_front = z > NEAR_PLANE
    zc = torch.where(in_front, z, torch.ones_like(z))
    grad_cam = means_grad @ rot.T  # covector: dL/dp_cam = R dL/dp_world
    grad_ndc = torch.stack([grad_cam[:, 0] * zc / fx * (0.5 * w), grad_cam[:, 1] * zc / fy * (0.5 * h)], dim=1)
    radius = RADIUS_SIGMAS * log_scales.max(dim=1).values.exp() * torch.maximum(fx, fy) / zc
    u = fx * cam[:, 0] / zc + cx
    v = fy * cam[:, 1] / zc + cy
    visible = in_front & (u + radius > 0) & (u - radius < w) & (v + radius > 0) & (v - radius < h)
    return grad_ndc.norm(dim=1), visible, torch.where(visible, radius, torch.zeros_like(radius))


def densify_and_prune(params: GaussianParameters, config: FitConfig, extent: float, prune_large: bool,
                      generator: "torch.Generator") -> dict:
    """Clone small and split large Gaussians with a high mean view-space gradient (up to the cap),
    then prune transparent ones (and oversized ones when ``prune_large``). Returns the counts."""
    import torch

    n0 = len(params)
    grads = params.stats["grad_accum"] / params.stats["grad_count"].clamp_min(1.0)
    max_scale = params.params["log_scales"].detach().max(dim=1).values.exp()
    candidates = grads >= config.densify_grad_threshold
    # the cap: keep only the strongest candidates that fit (a split adds split_count - 1 net)
    budget = config.max_gaussians - n0
    idx = torch.nonzero(candidates).reshape(-1)
    if idx.numel() > 0:
        order = torch.sort(grads[idx], descending=True, stable=True).indices
        idx = idx[order]
        small = max_scale[idx] <= config.percent_dense * extent
        cost = torch.where(small, 1, config.split_count - 1)
        fits = torch.cumsum(cost, 0) <= max(budget, 0)
        idx = idx[fits]
    chosen = torch.zeros(n0, dtype=torch.bool)
    chosen[idx] = True
    clone = chosen & (max_scale <= config.percent_dense * extent)
    split = chosen & ~clone

    p = {name: value.detach() for name, value in params.params.items()}
    new = {name: p[name][clone] for name in PARAMETER_NAMES}
    # split: children sampled from the parent Gaussian, scales divided by split_scale_divisor
    k = config.split_count
    if int(split.sum()) > 0:
        scales = p["log_scales"][split].exp().repeat(k, 1)
        samples = torch.randn(scales.shape, generator=generator) * scales
        q = normalized(p["quats"][split]).repeat(k, 1)
        children = {
            "means": torch.einsum("nij,nj->ni", quats_to_rotmats_torch(q), samples) + p["means"][split].repeat(k, 1),
            "log_scales": (scales / config.split_scale_divisor).log(),
            "quats": p["quats"][split].repeat(k, 1),
            "opacity_logits": p["opacity_logits"][split].repeat(k),
            "f_dc": p["f_dc"][split].repeat(k, 1, 1),
            "f_rest": p["f_rest"][split].repeat(k, 1, 1),
        }
        new = {name: torch.cat([new[name], children[name]], dim=0) for name in PARAMETER_NAMES}
    num_new = int(new["means"].shape[0])
    if num_new:
        params.append(new)
    # prune: the split parents, transparent Gaussians, oversized ones
    remove = torch.cat([split, torch.zeros(num_new, dtype=torch.bool)])
    opacity = torch.sigmoid(params.params["opacity_logits"].detach())
    transparent = opacity < config.prune_opacity
    remove |= transparent
    large = torch.zeros_like(remove)
    if prune_large:
        world = params.params["log_scales"].detach().max(dim=1).values.exp() > config.prune_world_scale * extent
        screen = params.stats["max_radius"] > config.prune_screen_size
        large = (world | screen) & ~remove
        remove |= large
    if bool(remove.all()):  # never prune everything: keep the most opaque Gaussian
        remove[torch.argmax(opacity)] = False
    params.select(~remove)
    params.reset_stats()
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned_transparent": int(transparent.sum()),
            "pruned_large": int(large.sum()), "gaussians": len(params)}


def reset_opacity(params: GaussianParameters, ceiling: float) -> None:
    """Clamp every opacity to at most ``ceiling`` and zero the opacity's Adam moments."""
    import torch

    logit = math.log(ceiling / (1.0 - ceiling))
    params.replace("opacity_logits", torch.minimum(params.params["opacity_logits"].detach(),
                                                    torch.tensor(logit)))
