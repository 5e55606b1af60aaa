"""Unit quaternions (w, x, y, z) <-> rotation matrices: one formula each way, numpy and torch entry points.

The numpy version serves the dataset side (``Gaussians``, augmentation), the torch version the renderer's
projection and the fit's densification (differentiable). Both build the matrix from ``_rotmat_entries``.
torch is imported only by the torch entry point, so the numpy side stays torch-free. The inverse,
:func:`rotmats_to_quats`, serves the training augmentation (rotated covariances back to quaternions).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

#: Quaternions recovered from rotation matrices: the largest of the four candidates is at least 1/2, so
#: this floor only protects against a non-orthonormal input.
QUAT_FROM_MATRIX_EPS = 1e-12


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


def rotmats_to_quats(rotmats: np.ndarray) -> np.ndarray:
    """``[N, 3, 3]`` rotation matrices -> ``[N, 4]`` unit quaternions (w, x, y, z) (Shepperd).

    The sign of each row is whatever the method gives; the network's inputs are made sign-canonical in
    one place for every path, ``ovgaussian.model.network.gaussian_attributes``."""
    r = np.asarray(rotmats, dtype=np.float64)
    trace = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    candidates = np.stack([trace, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    choice = np.argmax(candidates, axis=1)
    q = np.empty((r.shape[0], 4), dtype=np.float64)
    for k in range(4):
        rows = choice == k
        if not rows.any():
            continue
        m = r[rows]
        if k == 0:
            s = np.sqrt(np.maximum(1.0 + trace[rows], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([0.25 * s, (m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                                (m[:, 1, 0] - m[:, 0, 1]) / s], axis=1)
        elif k == 1:
            s = np.sqrt(np.maximum(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / s, 0.25 * s, (m[:, 0, 1] + m[:, 1, 0]) / s,
                                (m[:, 0, 2] + m[:, 2, 0]) / s], axis=1)
        elif k == 2:
            s = np.sqrt(np.maximum(1.0 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([(m[:, 0, 2] - m[:, 2, 0]) / s, (m[:, 0, 1] + m[:, 1, 0]) / s, 0.25 * s,
                                (m[:, 1, 2] + m[:, 2, 1]) / s], axis=1)
        else:
            s = np.sqrt(np.maximum(1.0 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([(m[:, 1, 0] - m[:, 0, 1]) / s, (m[:, 0, 2] + m[:, 2, 0]) / s,
                                (m[:, 1, 2] + m[:, 2, 1]) / s, 0.25 * s], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)
