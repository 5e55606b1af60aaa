"""Unit quaternions (w, x, y, z) -> rotation matrices: one formula, a numpy and a torch entry point.

The numpy version serves the dataset side (``Gaussians``, augmentation), the torch version the renderer's
projection and the fit's densification (differentiable). Both build the matrix from ``_rotmat_entries``.
torch is imported only by the torch entry point, so the numpy side stays torch-free.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch


def _rotmat_entries(w, x, y, z) -> list:
    """The nine entries of the rotation matrix of a unit quaternion, row-major (works on arrays and tensors)."""
    return [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]


def quats_to_rotmats(quats: np.ndarray) -> np.ndarray:
    """``[N, 4]`` unit quaternions (w, x, y, z) -> ``[N, 3, 3]`` rotation matrices (numpy).

    Computed in float64; returned in the input's dtype when it is float32/float64, else float64."""
    w, x, y, z = (quats[:, i].astype(np.float64) for i in range(4))
    r = np.stack(_rotmat_entries(w, x, y, z), axis=-1)
    return r.reshape(-1, 3, 3).astype(quats.dtype if quats.dtype in (np.float32, np.float64) else np.float64)


def quats_to_rotmats_torch(quats: "torch.Tensor") -> "torch.Tensor":
    """``[N, 4]`` unit quaternions (w, x, y, z) -> ``[N, 3, 3]`` (torch, differentiable, in the input's dtype)."""
    import torch  # heavy: only where tensors are asked for

    return torch.stack(_rotmat_entries(*quats.unbind(-1)), dim=-1).reshape(-1, 3, 3)
