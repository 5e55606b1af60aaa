"""Packing of sparse sites ``(batch, x, y, z)`` into one int64 key, ordered lexicographically.

Shared by the site sets (``voxelize.py``) and the kernel maps built from their keys (``kernel_map.py``).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Bits per coordinate in a packed key. Coordinates live in [-2^15, 2^15).
COORD_BITS = 16
#: Added to every coordinate so that the packed field is non-negative.
COORD_OFFSET = 1 << (COORD_BITS - 1)
#: Coordinates must stay this far inside the packed range so that neighbour keys computed as
#: ``key + delta`` (kernel offsets up to +-KEY_MARGIN, i.e. kernels up to 17^3) never carry into
#: the next field and alias another site.
KEY_MARGIN = 8
#: Smallest and largest coordinate accepted at any level.
COORD_MIN = -COORD_OFFSET + KEY_MARGIN
COORD_MAX = COORD_OFFSET - 1 - KEY_MARGIN
#: Largest batch index: the batch lives in the top bits above the three coordinate fields
#: (63 - 48 = 15 bits, keys stay positive).
BATCH_MAX = (1 << (63 - 3 * COORD_BITS)) - 1


def pack_keys(batch_index: Tensor, coords: Tensor) -> Tensor:
    """``[M]`` int64 keys, increasing in lexicographic ``(batch, x, y, z)`` order.

    Args:
        batch_index: ``[M]`` integer scene index in ``[0, BATCH_MAX]``.
        coords: ``[M, 3]`` integer voxel coordinates in ``[COORD_MIN, COORD_MAX]``.
    """
    coords = coords.long()
    batch_index = batch_index.long()
    if coords.numel():
        lo, hi = int(coords.min()), int(coords.max())
        if lo < COORD_MIN or hi > COORD_MAX:
            raise ValueError(
                f"voxel coordinates span [{lo}, {hi}], outside the supported [{COORD_MIN}, {COORD_MAX}]; "
                "use a larger voxel size"
            )
        blo, bhi = int(batch_index.min()), int(batch_index.max())
        if blo < 0 or bhi > BATCH_MAX:
            raise ValueError(f"batch_index spans [{blo}, {bhi}], outside [0, {BATCH_MAX}]")
    c = coords + COORD_OFFSET
    return (
        (batch_index << (3 * COORD_BITS))
        | (c[:, 0] << (2 * COORD_BITS))
        | (c[:, 1] << COORD_BITS)
        | c[:, 2]
    )


def unpack_keys(keys: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`pack_keys`: ``(batch_index [M], coords [M, 3])``."""
    mask = (1 << COORD_BITS) - 1
    x = ((keys >> (2 * COORD_BITS)) & mask) - COORD_OFFSET
    y = ((keys >> COORD_BITS) & mask) - COORD_OFFSET
    z = (keys & mask) - COORD_OFFSET
    return keys >> (3 * COORD_BITS), torch.stack([x, y, z], dim=1)


def offset_key_delta(offset: tuple[int, int, int]) -> int:
    """Key difference between a site and its neighbour at ``offset`` (valid inside the margin)."""
    dx, dy, dz = offset
    return (dx << (2 * COORD_BITS)) + (dy << COORD_BITS) + dz
