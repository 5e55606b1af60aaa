"""Semantic and instance label maps from per-pixel blend weights (majority by accumulated weight)."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from seggaussian.constants import IGNORE_LABEL
from seggaussian.render.blend import BlendWeights

#: A pixel whose accumulated alpha (all contributors, captured or residual) is below this gets
#: IGNORE_LABEL: it shows mostly background, so no Gaussian label is trustworthy there.
LABEL_MIN_ALPHA = 0.5


class LabelMaps(NamedTuple):
    """Label images of one view.

    Fields:
        semantic: ``[H, W]`` int64 class id with the largest accumulated weight, or IGNORE_LABEL.
        instance: ``[H, W]`` int64 instance id with the largest accumulated weight, or IGNORE_LABEL.
        soft: ``[H, W, C]`` float32 accumulated blend weight per class (IGNORE-labelled Gaussians add
            to no class).
    """

    semantic: Tensor
    instance: Tensor
    soft: Tensor


def _majority(labels: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Per pixel, the label whose slots carry the most weight. labels/weights: [H, W, K].

    Slots with weight 0 (unused, or IGNORE-labelled) never win; ties go to the earlier (front-most) slot.
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
) -> LabelMaps:
    """Each pixel takes the label with the largest accumulated blend weight among its K contributors.

    IGNORE_LABEL where the pixel's accumulated alpha (``weights.sum + residual_alpha``) is below
    ``min_alpha`` or where no captured contributor carries a label.
    """
    semantic = torch.as_tensor(semantic).to(torch.int64).reshape(-1)
    instance = torch.as_tensor(instance).to(torch.int64).reshape(-1)
    n = semantic.shape[0]
    if instance.shape[0] != n:
        raise ValueError(f"render_label_maps: semantic has {n} entries but instance has {instance.shape[0]}")
    ids, weights = blend.ids, blend.weights.to(torch.float32)
    used = ids >= 0
    if used.any() and int(ids.max()) >= n:
        raise ValueError(f"render_label_maps: blend weights refer to Gaussian {int(ids.max())} but only {n} labels")
    sem_ok = (semantic >= 0) & (semantic < num_classes)
    bad = ~sem_ok & (semantic != IGNORE_LABEL)
    if bool(bad.any()):
        raise ValueError(
            f"render_label_maps: {int(bad.sum())} semantic labels outside 0..{num_classes - 1} and not IGNORE_LABEL"
        )
    safe = ids.clamp_min(0)
    sem = torch.where(used, semantic[safe], torch.full_like(ids, IGNORE_LABEL))
    inst = torch.where(used, instance[safe], torch.full_like(ids, IGNORE_LABEL))
    w_sem = torch.where(used & (sem != IGNORE_LABEL), weights, torch.zeros_like(weights))
    w_inst = torch.where(used & (inst != IGNORE_LABEL), weights, torch.zeros_like(weights))

    height, width, _ = ids.shape
    soft = torch.zeros(height, width, num_classes, dtype=torch.float32)
    soft.scatter_add_(-1, torch.where(sem == IGNORE_LABEL, torch.zeros_like(sem), sem), w_sem)

    total_alpha = weights.sum(-1) + blend.residual_alpha.to(torch.float32)
    opaque = total_alpha >= min_alpha
    ignore = torch.full((height, width), IGNORE_LABEL, dtype=torch.int64)
    sem_best, sem_weight = _majority(sem, w_sem)
    inst_best, inst_weight = _majority(inst, w_inst)
    semantic_map = torch.where(opaque & (sem_weight > 0), sem_best, ignore)
    instance_map = torch.where(opaque & (inst_weight > 0), inst_best, ignore)
    return LabelMaps(semantic_map, instance_map, soft)
