"""Semantic and instance label maps from per-pixel blend weights (majority by accumulated weight).

The vote counts IGNORE_LABEL as a label of its own: an unlabelled Gaussian contributes its blend
weight to "ignore" like any other label, so an opaque unlabelled Gaussian in front of a labelled one
makes the pixel ignore (what a raycast of the labelled mesh gives there: the first surface hit has
no label). Front-most contributors carry the largest weights (alpha compositing), so the winner is
the label of what is in front, not of a surface hidden behind it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render.labelmaps_numba import vote_kernel
from seggaussian.render.results import BlendWeights

#: A pixel whose accumulated alpha (all contributors, captured or residual) is below this gets
#: IGNORE_LABEL: it shows mostly background, so no Gaussian label is trustworthy there.
LABEL_MIN_ALPHA = 0.5


class LabelMaps(NamedTuple):
    """Label images of one view.

    Fields:
        semantic: ``[H, W]`` int64 class id with the largest accumulated weight, or IGNORE_LABEL (ignore
            won the vote, or the pixel is mostly background).
        instance: ``[H, W]`` int64 instance id with the largest accumulated weight, or IGNORE_LABEL (same rule).
        soft: ``[H, W, C]`` float32 accumulated blend weight per class (IGNORE-labelled Gaussians add
            to no class).
    """

    semantic: Tensor
    instance: Tensor
    soft: Tensor


def _majority(labels: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Per pixel, the label whose slots carry the most weight. labels/weights: [H, W, top_k].

    IGNORE_LABEL slots vote like any label. Slots with weight 0 (unused) never win; ties go to the
    earlier (front-most) slot.
    Returns (label [H, W], its total weight [H, W]).
    """
    total = torch.zeros_like(weights)
    for k in range(labels.shape[-1]):
        total = total + weights[..., k : k + 1] * (labels == labels[..., k : k + 1])
    total = torch.where(weights > 0, total, torch.full_like(total, -1.0))
    best_total, best_slot = total.max(-1)  # first maximum: front-most slot
    return torch.gather(labels, -1, best_slot[..., None])[..., 0], best_total


def render_label_maps(
    blend: BlendWeights,
    semantic: Tensor,  # [N] int class ids, IGNORE_LABEL for unlabelled
    instance: Tensor,  # [N] int instance ids, IGNORE_LABEL for none
    num_classes: int,
    min_alpha: float = LABEL_MIN_ALPHA,
    backend: str = "auto",
) -> LabelMaps:
    """Each pixel takes the label with the largest accumulated blend weight among its top_k contributors,
    IGNORE_LABEL counted as a label of its own (unlabelled Gaussians occlude).

    IGNORE_LABEL where ignore wins, where the pixel's accumulated alpha (``weights.sum + residual_alpha``)
    is below ``min_alpha``, or where no captured contributor has weight. ``backend``: ``fast`` (numba, one
    pass per pixel), ``reference`` (vectorized torch, obviously correct) or ``auto`` (fast).
    """
    if backend == "reference":
        return render_label_maps_reference(blend, semantic, instance, num_classes, min_alpha)
    if backend not in ("auto", "fast"):
        raise ValueError(f"render_label_maps: backend must be auto, fast or reference, got {backend!r}")
    semantic, instance = _check_labels(blend, semantic, instance, num_classes)
    ids = blend.ids.to(torch.int64).contiguous().numpy()
    weights = blend.weights.to(torch.float32).contiguous().numpy()
    height, width, top_k = ids.shape
    residual = blend.residual_alpha.to(torch.float32).reshape(-1).contiguous().numpy()
    sem_out = np.empty(height * width, np.int64)
    inst_out = np.empty(height * width, np.int64)
    soft = np.zeros((height * width, num_classes), np.float32)
    vote_kernel(ids.reshape(-1, top_k), weights.reshape(-1, top_k), residual, semantic.numpy(), instance.numpy(),
                np.float32(min_alpha), IGNORE_LABEL, sem_out, inst_out, soft)
    sem_out, inst_out = sem_out.reshape(height, width), inst_out.reshape(height, width)
    soft = soft.reshape(height, width, num_classes)
    return LabelMaps(torch.from_numpy(sem_out), torch.from_numpy(inst_out), torch.from_numpy(soft))


def _check_labels(blend: BlendWeights, semantic, instance, num_classes: int) -> tuple[Tensor, Tensor]:
    """Labels as flat int64 tensors, after checking they fit the blend weights and the class count."""
    semantic, instance = check_labels(None, semantic, instance, num_classes, "render_label_maps")
    n = semantic.shape[0]
    ids = blend.ids
    if (ids >= 0).any() and int(ids.max()) >= n:
        raise ValueError(f"render_label_maps: blend weights refer to Gaussian {int(ids.max())} but only {n} labels")
    return semantic, instance


def check_labels(num_gaussians: int | None, semantic, instance, num_classes: int, what: str) -> tuple[Tensor, Tensor]:
    """Per-Gaussian labels as flat int64 tensors, or a one-line ``ValueError`` (``what``: the caller's name): as many
    semantic as instance labels (and as ``num_gaussians`` when given), every semantic label a class id below
    ``num_classes`` or IGNORE_LABEL."""
    semantic = torch.as_tensor(semantic).to(torch.int64).reshape(-1)
    instance = torch.as_tensor(instance).to(torch.int64).reshape(-1)
    n = semantic.shape[0]
    if instance.shape[0] != n:
        raise ValueError(f"{what}: semantic has {n} entries but instance has {instance.shape[0]}")
    if num_gaussians is not None and n != num_gaussians:
        raise ValueError(f"{what}: {n} labels for {num_gaussians} Gaussians")
    bad = ~((semantic >= 0) & (semantic < num_classes)) & (semantic != IGNORE_LABEL)
    if bool(bad.any()):
        raise ValueError(f"{what}: {int(bad.sum())} semantic labels outside 0..{num_classes - 1} and not IGNORE_LABEL")
    return semantic, instance


def render_label_maps_reference(
    blend: BlendWeights,
    semantic: Tensor,  # [N] int class ids, IGNORE_LABEL for unlabelled
    instance: Tensor,  # [N] int instance ids, IGNORE_LABEL for none
    num_classes: int,
    min_alpha: float = LABEL_MIN_ALPHA,
) -> LabelMaps:
    """The vectorized torch reference of ``render_label_maps`` (same rule, same tie-breaking)."""
    semantic, instance = _check_labels(blend, semantic, instance, num_classes)
    ids, weights = blend.ids, blend.weights.to(torch.float32)
    used = ids >= 0
    safe = ids.clamp_min(0)
    sem = torch.where(used, semantic[safe], torch.full_like(ids, IGNORE_LABEL))
    inst = torch.where(used, instance[safe], torch.full_like(ids, IGNORE_LABEL))
    w_used = torch.where(used, weights, torch.zeros_like(weights))  # ignore-labelled slots vote too
    w_class = torch.where(used & (sem != IGNORE_LABEL), weights, torch.zeros_like(weights))

    height, width, _ = ids.shape
    soft = torch.zeros(height, width, num_classes, dtype=torch.float32)
    soft.scatter_add_(-1, torch.where(sem == IGNORE_LABEL, torch.zeros_like(sem), sem), w_class)

    total_alpha = weights.sum(-1) + blend.residual_alpha.to(torch.float32)
    opaque = total_alpha >= min_alpha
    ignore = torch.full((height, width), IGNORE_LABEL, dtype=torch.int64)
    sem_best, sem_weight = _majority(sem, w_used)
    inst_best, inst_weight = _majority(inst, w_used)
    semantic_map = torch.where(opaque & (sem_weight > 0), sem_best, ignore)
    instance_map = torch.where(opaque & (inst_weight > 0), inst_best, ignore)
    return LabelMaps(semantic_map, instance_map, soft)
