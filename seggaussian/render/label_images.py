"""Label images of a view straight from the Gaussians: the label-map vote done inside the blend-weight walk.

``render_label_images`` gives the semantic and instance maps of ``render_label_maps(compute_blend_weights(...))``
without the ``[H, W, top_k]`` ids and weights or the ``[H, W, C]`` soft sums in between: each tile votes on its own
pixels' slots as soon as its walk ends, and a pixel stops walking once nothing behind can change its vote
(``labelmaps_numba``, "walk_vote_kernel"). The maps are equal, bit for bit; ``backend="reference"`` is the two-step
path itself, kept beside it for the tests.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render.blend import DEFAULT_TOP_K, compute_blend_weights
from seggaussian.render.inputs import check_inputs
from seggaussian.render.labelmaps import LABEL_MIN_ALPHA, check_labels, render_label_maps
from seggaussian.render.parallel import run_parallel
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.tiles import bin_gaussians


class LabelImages(NamedTuple):
    """The label maps of one view.

    Fields:
        semantic: ``[H, W]`` int64 class id with the largest accumulated weight among the ``top_k`` front-most
            contributors, or IGNORE_LABEL (ignore won, or the pixel's accumulated alpha is below ``min_alpha``).
        instance: ``[H, W]`` int64 instance id, same rule.
    """

    semantic: Tensor
    instance: Tensor


def render_label_images(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] world -> camera (OpenCV)
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    semantic: Tensor,  # [N] int class ids, IGNORE_LABEL for unlabelled
    instance: Tensor,  # [N] int instance ids, IGNORE_LABEL for none
    num_classes: int,
    top_k: int = DEFAULT_TOP_K,
    min_alpha: float = LABEL_MIN_ALPHA,
    *,
    backend: str = "auto",
) -> LabelImages:
    """The semantic and instance maps of ``render_label_maps(compute_blend_weights(..., top_k), ..., min_alpha)``.

    ``backend``: ``fast`` (one compiled walk that votes per tile), ``reference`` (the two steps, blend weights then
    the vote) or ``auto`` (fast)."""
    if backend == "reference":
        blend = compute_blend_weights(means, quats, log_scales, opacity_logits, viewmat, K, width, height, top_k)
        maps = render_label_maps(blend, semantic, instance, num_classes, min_alpha)
        return LabelImages(maps.semantic, maps.instance)
    if backend not in ("auto", "fast"):
        raise ValueError(f"render_label_images: backend must be auto, fast or reference, got {backend!r}")
    if int(top_k) < 1:
        raise ValueError(f"render_label_images: top_k must be >= 1, got {top_k}")
    from seggaussian.render.labelmaps_numba import walk_vote_kernel

    width, height, top_k = int(width), int(height), int(top_k)
    with torch.no_grad():
        check_inputs(means, quats, log_scales, opacity_logits, viewmat, K, width, height)
        semantic, instance = check_labels(len(means), semantic, instance, num_classes, "render_label_images")
        opacities = torch.sigmoid(opacity_logits.to(torch.float32))
        projection = project_gaussians_fast(means, quats, log_scales, viewmat, K, width, height)
        bins = bin_gaussians(projection, width, height, opacities)
        sem_out = np.full((height, width), IGNORE_LABEL, np.int64)
        inst_out = np.full((height, width), IGNORE_LABEL, np.int64)
        if bins.num_intersections:
            run_parallel(walk_vote_kernel, _as_np(projection.means2d), _as_np(projection.conics), _as_np(opacities),
                         bins.rows, bins.offsets, bins.gaussian_ids, bins.tiles_x, width, height, top_k, semantic.numpy(),
                         instance.numpy(), np.float32(min_alpha), IGNORE_LABEL, sem_out, inst_out)
    return LabelImages(torch.from_numpy(sem_out), torch.from_numpy(inst_out))


def _as_np(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)
