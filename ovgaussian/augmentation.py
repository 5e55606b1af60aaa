"""Training augmentation of OVGaussian: a random similarity applied to the network's input Gaussians.

A similarity ``A`` (random uniform scale, rotation about the up axis z, mirror of x and/or y) maps means to
``A x`` and covariances to ``A Sigma A^T`` (quaternions and log-scales updated). It is applied to the
network input only: applying the same ``A`` to the camera would leave the rendered image unchanged (a
similarity of scene and camera together does not change any pixel), so the blend weights computed on the
stored geometry stay exact and ``M = W S`` needs no re-rasterization.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ovgaussian.train_config import DataConfig
from seggaussian.rotations import quats_to_rotmats, rotmats_to_quats


class Augmentation(NamedTuple):
    """A similarity ``x -> scale * flip @ rot_z @ x`` about the scene centre.

    Fields:
        scale: uniform scale factor (> 0).
        angle: rotation about z in radians.
        flip: ``[3]`` signs (+-1 on x and y, +1 on z).
    """

    scale: float
    angle: float
    flip: np.ndarray

    @property
    def linear(self) -> np.ndarray:
        """``[3, 3]`` matrix ``scale * diag(flip) @ R_z(angle)``."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return self.scale * np.diag(self.flip) @ rot

    @classmethod
    def identity(cls) -> "Augmentation":
        return cls(1.0, 0.0, np.ones(3))


def sample_augmentation(rng: np.random.Generator, config: DataConfig) -> Augmentation:
    """Random scale in ``scale_range``, angle in [0, 2 pi), x/y mirrors with ``flip_probability``."""
    if not config.augment:
        return Augmentation.identity()
    low, high = config.scale_range
    scale = float(rng.uniform(low, high))
    angle = float(rng.uniform(0.0, 2.0 * np.pi))
    flips = rng.random(2) < config.flip_probability
    flip = np.array([-1.0 if flips[0] else 1.0, -1.0 if flips[1] else 1.0, 1.0])
    return Augmentation(scale, angle, flip)


def augment_gaussians(
    means: np.ndarray,  # [N, 3] recentred
    quats: np.ndarray,  # [N, 4] unit, w x y z
    log_scales: np.ndarray,  # [N, 3]
    augmentation: Augmentation,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means, quaternions and log-scales of the Gaussians mapped by the similarity (float32 out).

    Covariance ``R S^2 R^T`` becomes ``A R S^2 R^T A^T``: with ``A = s F R_z`` the new rotation is
    ``F R_z R D`` where ``D = diag(det F, 1, 1)`` makes it proper (D commutes with ``S``), and the
    log-scales grow by ``log s``.
    """
    linear = augmentation.linear
    new_means = (means.astype(np.float64) @ linear.T).astype(np.float32)
    orthogonal = linear / augmentation.scale  # F R_z, det = det F
    rotmats = np.einsum("ij,njk->nik", orthogonal, quats_to_rotmats(quats.astype(np.float64)))
    if float(np.prod(augmentation.flip)) < 0:
        rotmats[:, :, 0] *= -1.0  # R D with D = diag(-1, 1, 1): proper again, same covariance
    new_quats = rotmats_to_quats(rotmats).astype(np.float32)
    new_log_scales = (log_scales.astype(np.float64) + np.log(augmentation.scale)).astype(np.float32)
    return new_means, new_quats, new_log_scales
