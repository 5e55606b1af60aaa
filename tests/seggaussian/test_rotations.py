"""The one quaternion -> rotation matrix formula: numpy and torch entry points agree with each other and
with an independent implementation (scipy)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from seggaussian.fit import optimize as fit

from seggaussian.core import gaussians
from seggaussian.render import projection
from seggaussian.core.rotations import quats_to_rotmats, quats_to_rotmats_torch


def unit_quats(n: int, seed: int) -> np.ndarray:  # [n, 4] (w, x, y, z), with the axis-aligned cases
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q = np.concatenate([q, np.eye(4), -np.eye(4)])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_numpy_matches_scipy():
    q = unit_quats(500, 0)
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy: scalar last
    np.testing.assert_allclose(quats_to_rotmats(q), expected, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_and_torch_agree(dtype):
    q = unit_quats(500, 1).astype(dtype)
    r_np = quats_to_rotmats(q)
    r_t = quats_to_rotmats_torch(torch.from_numpy(q))
    assert r_np.dtype == dtype and r_t.dtype == torch.from_numpy(q).dtype and r_t.shape == (508, 3, 3)
    np.testing.assert_allclose(r_t.numpy(), r_np, atol=1e-6 if dtype == np.float32 else 1e-12)


def test_torch_is_differentiable():
    q = torch.from_numpy(unit_quats(8, 2)).requires_grad_(True)
    assert torch.autograd.gradcheck(quats_to_rotmats_torch, (q,))


def test_no_other_copy():
    assert gaussians.quats_to_rotmats is quats_to_rotmats
    assert not hasattr(projection, "quats_to_rotmats") and not hasattr(fit, "quats_to_rotmats")


def test_empty():
    assert quats_to_rotmats(np.zeros((0, 4))).shape == (0, 3, 3)
    assert quats_to_rotmats_torch(torch.zeros(0, 4)).shape == (0, 3, 3)
