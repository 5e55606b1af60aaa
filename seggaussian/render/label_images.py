"""Label images of a view straight from the Gaussians: the label-map vote done inside the blend-weight walk.

``render_label_images`` gives the semantic and instance maps of ``render_label_maps(compute_blend_weights(...))``
without the ``[H, W, top_k]`` ids and weights or the ``[H, W, C]`` soft sums in between: each tile votes on its own
pixels' slots as soon as its walk ends, and a pixel stops walking once nothing behind can change its vote
(``labelmaps_numba``, "walk_vote_kernel"). Only the Gaussians that may reach the image are projected
(``screen_cull``), and a scene's checks and per-Gaussian constants are done once for all its views
(``prepare_label_scene``). The maps are equal, bit for bit; ``backend="reference"`` is the two-step
path itself, kept beside it for the tests.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render.blend import DEFAULT_TOP_K, compute_blend_weights
from seggaussian.render.inputs import check_camera, check_gaussians
from seggaussian.render.labelmaps import LABEL_MIN_ALPHA, check_labels, render_label_maps
from seggaussian.render.labelmaps_numba import walk_vote_kernel
from seggaussian.render.parallel import run_parallel
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.rasterize_numba import _as_np
from seggaussian.render.screen_cull import largest_scales, screen_candidates
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


class LabelScene(NamedTuple):
    """The Gaussians of a scene checked and prepared once for :func:`render_label_scene` (:func:`prepare_label_scene`).

    Fields: ``means [N, 3]``, ``quats [N, 4]``, ``log_scales [N, 3]`` as given; ``opacities [N]`` float32 (the
    sigmoid of the logits); ``semantic``/``instance`` ``[N]`` int64 (checked against ``num_classes``); ``scales [N]``
    float64, each Gaussian's largest scale (``screen_cull.largest_scales``)."""

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacities: Tensor
    semantic: np.ndarray
    instance: np.ndarray
    scales: np.ndarray


def prepare_label_scene(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, semantic: Tensor,
                        instance: Tensor, num_classes: int) -> LabelScene:
    """Check the Gaussians and their labels once (one-line ``ValueError``s) and keep what every view's walk needs."""
    check_gaussians(means, quats, log_scales, opacity_logits)
    semantic, instance = check_labels(len(means), semantic, instance, num_classes, "render_label_images")
    with torch.no_grad():
        opacities = torch.sigmoid(opacity_logits.to(torch.float32))
    return LabelScene(means, quats, log_scales, opacities, semantic.numpy(), instance.numpy(),
                      largest_scales(log_scales.detach().cpu().numpy()))


def render_label_scene(scene: LabelScene, viewmat: Tensor, K: Tensor, width: int, height: int,
                       top_k: int = DEFAULT_TOP_K, min_alpha: float = LABEL_MIN_ALPHA) -> LabelImages:
    """One view's label images (the fast path of :func:`render_label_images`): the Gaussians that may reach the image
    (``screen_cull.screen_candidates``) projected, binned and walked, voting per tile."""
    if int(top_k) < 1:
        raise ValueError(f"render_label_images: top_k must be >= 1, got {top_k}")
    width, height, top_k = int(width), int(height), int(top_k)
    check_camera(viewmat, K, width, height)
    sem_out = np.full((height, width), IGNORE_LABEL, np.int64)
    inst_out = np.full((height, width), IGNORE_LABEL, np.int64)
    with torch.no_grad():
        rows = screen_candidates(scene.means.detach().cpu().numpy(), scene.scales, viewmat.detach().cpu().numpy(),
                                 K.detach().cpu().numpy(), width, height)
        index = torch.from_numpy(rows)  # ascending: equal depths keep their order in the tile lists
        opacities = scene.opacities[index]
        projection = project_gaussians_fast(scene.means[index], scene.quats[index], scene.log_scales[index], viewmat,
                                            K, width, height)
        bins = bin_gaussians(projection, width, height, opacities)
        if bins.num_intersections:
            run_parallel(walk_vote_kernel, _as_np(projection.means2d), _as_np(projection.conics), _as_np(opacities),
                         bins.rows, bins.offsets, bins.gaussian_ids, bins.tiles_x, width, height, top_k,
                         scene.semantic[rows], scene.instance[rows], np.float32(min_alpha), IGNORE_LABEL, sem_out,
                         inst_out)
    return LabelImages(torch.from_numpy(sem_out), torch.from_numpy(inst_out))


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

    ``backend``: ``fast`` (one compiled walk that votes per tile, over the Gaussians that may reach the image),
    ``reference`` (the two steps over every Gaussian: blend weights, then the vote) or ``auto`` (fast). Many views of
    one scene: :func:`prepare_label_scene` once, then :func:`render_label_scene` per view."""
    if backend == "reference":
        blend = compute_blend_weights(means, quats, log_scales, opacity_logits, viewmat, K, width, height, top_k)
        maps = render_label_maps(blend, semantic, instance, num_classes, min_alpha)
        return LabelImages(maps.semantic, maps.instance)
    if backend not in ("auto", "fast"):
        raise ValueError(f"render_label_images: backend must be auto, fast or reference, got {backend!r}")
    scene = prepare_label_scene(means, quats, log_scales, opacity_logits, semantic, instance, num_classes)
    return render_label_scene(scene, viewmat, K, width, height, top_k, min_alpha)
