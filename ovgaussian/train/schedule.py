"""The training schedule of OVGaussian: which scenes each step trains on, which process takes which, the
generator seed of each sample, and the learning rate of each step.

Every draw depends on (seed, epoch, step, scene id) only, never on the number of processes: a global batch
is cut into contiguous per-rank slices (:func:`rank_slice`), and each scene's view, augmentation and pixels
come from a generator seeded by :func:`sample_seed`.
"""

from __future__ import annotations

import hashlib
import math
from typing import Sequence

import numpy as np

#: Exponent of the polynomial learning-rate decay (``lr * (1 - t)^power``).
POLY_POWER = 0.9


def learning_rate(step: int, total_steps: int, base_lr: float, schedule: str) -> float:
    """Learning rate of optimizer step ``step`` (0-based) out of ``total_steps``."""
    if schedule == "constant" or total_steps <= 0:
        return base_lr
    t = min(max(step / total_steps, 0.0), 1.0)
    if schedule == "cosine":
        return base_lr * 0.5 * (1.0 + math.cos(math.pi * t))
    if schedule == "poly":
        return base_lr * (1.0 - t) ** POLY_POWER
    raise ValueError(f"unknown learning-rate schedule {schedule!r} (cosine, poly or constant)")


def sample_seed(seed: int, epoch: int, step: int, scene_id: str) -> list[int]:
    """Entropy of the generator of one scene of one step (rank-independent)."""
    digest = int.from_bytes(hashlib.sha256(scene_id.encode()).digest()[:4], "little")
    return [int(seed), int(epoch), int(step), digest]


def epoch_batches(scene_ids: Sequence[str], batch_scenes: int, seed: int, epoch: int) -> list[list[str]]:
    """The epoch's scene order (seeded permutation) cut into batches of ``batch_scenes`` (last may be short)."""
    if batch_scenes < 1:
        raise ValueError(f"batch_scenes must be >= 1, got {batch_scenes}")
    order = np.random.default_rng([int(seed), int(epoch), 0x5CE4E]).permutation(len(scene_ids))
    ids = [scene_ids[i] for i in order]
    return [ids[i:i + batch_scenes] for i in range(0, len(ids), batch_scenes)]


def rank_slice(batch: Sequence[str], rank: int, world_size: int) -> list[str]:
    """The contiguous part of a global batch a process handles (may be empty)."""
    bounds = np.linspace(0, len(batch), world_size + 1).round().astype(int)
    return list(batch[bounds[rank]:bounds[rank + 1]])
