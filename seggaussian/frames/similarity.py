"""Similarity transforms ``x -> scale * rotation @ x + translation`` and moving Gaussians by one.

``rotation`` is orthogonal: a proper rotation (det +1) or a reflection (det -1, e.g. a change of handedness between
axis conventions). ``transform_gaussians`` moves every part of a Gaussian consistently:

- means: ``x' = s M x + t`` (``M`` = ``rotation``);
- covariances: ``S' = s^2 M S M^T``. Gaussians store a rotation ``R_g`` (quaternion) and per-axis scales; with
  ``Q = M`` for a rotation and ``Q = -M`` for a reflection (``Q`` is then a proper rotation and
  ``Q S Q^T = M S M^T``), the new rotation is ``Q R_g`` and the log-scales grow by ``log s``;
- view-dependent colour: the view direction becomes ``M d``, so SH bands 1..3 are rotated by ``D_l(Q)`` and, for a
  reflection, multiplied by ``(-1)^l`` (see ``sh_rotation``): ``colour'(M d) == colour(d)``;
- opacities and ``extras`` are kept as they are (extras are copied by reference; none is geometric today).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seggaussian.frames.sh_rotation import (
    apply_sh_matrix,
    band_slice,
    check_orthogonal,
    rotate_sh_reference,
    sh_rotation_matrix,
)
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.rotations import quats_to_rotmats, rotmats_to_quats

#: ``from_matrix`` accepts a 3x3 block ``A`` as ``s * orthogonal`` when ``max |A^T A / s^2 - I| <= SIMILARITY_TOL``
#: (``s^2`` the mean eigenvalue of ``A^T A``): matrices written to JSON with ~6 significant digits deviate by ~1e-6;
#: a shear or a non-uniform scale (which no Gaussian can follow) deviates by far more.
SIMILARITY_TOL = 1e-5
#: ``from_matrix`` requires the last row to be ``0 0 0 1`` within this (absolute; exact in every file we know).
LAST_ROW_TOL = 1e-9
#: A 3x3 block whose ``|det|`` is below this is degenerate (scale ~1e-4 or less: not a frame change).
MIN_ABS_DET = 1e-12
#: ``is_identity`` tolerance (absolute, on the 4x4 matrix): round-off of composing a transform with its inverse.
IDENTITY_TOL = 1e-9


def similarity_problem(m) -> str | None:
    """None when ``m`` is a 4x4 similarity matrix (reflections allowed), else what is wrong with it (one line)."""
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        return "expected a 4x4 matrix of numbers"
    if a.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {a.shape}"
    if not np.isfinite(a).all():
        return "holds NaN/Inf"
    if np.abs(a[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > LAST_ROW_TOL:
        return f"last row must be 0 0 0 1, got {a[3].tolist()}"
    linear = a[:3, :3]
    det = float(np.linalg.det(linear))
    if abs(det) < MIN_ABS_DET:
        return f"the 3x3 block is singular (det {det:.3g}), not a similarity"
    gram = linear.T @ linear
    error = float(np.abs(gram / (np.trace(gram) / 3.0) - np.eye(3)).max())
    if error > SIMILARITY_TOL:
        return (f"the 3x3 block is not a uniform scale times a rotation (max |A^T A / s^2 - I| = {error:.3g} > "
                f"{SIMILARITY_TOL}): shear or non-uniform scale")
    return None


@dataclass(frozen=True, eq=False)
class Similarity:
    """``x -> scale * rotation @ x + translation``.

    Fields:
        rotation: ``[3, 3]`` float64 orthogonal matrix (det +1, or -1 for a reflection).
        translation: ``[3]`` float64.
        scale: positive uniform scale.
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    def __post_init__(self) -> None:
        rotation = check_orthogonal(self.rotation, "Similarity.rotation").copy()
        translation = np.array(self.translation, dtype=np.float64).reshape(-1)
        if translation.shape != (3,) or not np.isfinite(translation).all():
            raise ValueError(f"Similarity.translation: expected 3 finite numbers, got {self.translation!r}")
        scale = float(self.scale)
        if not (np.isfinite(scale) and scale > 0.0):
            raise ValueError(f"Similarity.scale: expected a positive finite number, got {self.scale!r}")
        rotation.flags.writeable = False
        translation.flags.writeable = False
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)
        object.__setattr__(self, "scale", scale)

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def identity(cls) -> "Similarity":
        return cls(np.eye(3), np.zeros(3), 1.0)

    @classmethod
    def from_matrix(cls, m, *, source: str = "matrix") -> "Similarity":
        """From a 4x4 ``[[s M, t], [0 0 0 1]]``; ValueError (one line, starting with ``source``) otherwise.

        The orthogonal part is the nearest orthogonal matrix (polar decomposition, sign of the determinant kept), so
        a matrix rounded in a text file comes back exactly orthogonal; a reflection is accepted (``is_reflection``).
        """
        problem = similarity_problem(m)
        if problem is not None:
            raise ValueError(f"{source}: {problem}")
        a = np.asarray(m, dtype=np.float64)
        linear = a[:3, :3]
        scale = float(np.sqrt(np.trace(linear.T @ linear) / 3.0))
        u, _, vt = np.linalg.svd(linear)
        return cls(u @ vt, a[:3, 3], scale)

    # --- views -------------------------------------------------------------------------------
    @property
    def matrix(self) -> np.ndarray:
        """``[4, 4]`` float64 homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    @property
    def is_reflection(self) -> bool:
        """True when the orthogonal part has det -1 (handedness changes)."""
        return bool(np.linalg.det(self.rotation) < 0.0)

    @property
    def proper_rotation(self) -> np.ndarray:
        """``Q``: ``rotation`` for a rotation, ``-rotation`` for a reflection (det +1 either way)."""
        return -self.rotation if self.is_reflection else self.rotation.copy()

    @property
    def is_identity(self) -> bool:
        return bool(np.abs(self.matrix - np.eye(4)).max() <= IDENTITY_TOL)

    def apply(self, points) -> np.ndarray:
        """``[P, 3]`` points mapped (float64)."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * (p @ self.rotation.T) + self.translation

    # --- algebra -----------------------------------------------------------------------------
    def inverse(self) -> "Similarity":
        """``x -> (1/s) M^T (x - t)``."""
        return Similarity(self.rotation.T, -(self.rotation.T @ self.translation) / self.scale, 1.0 / self.scale)

    def compose(self, other: "Similarity") -> "Similarity":
        """``self o other``: apply ``other`` first, then ``self``."""
        return Similarity(
            self.rotation @ other.rotation,
            self.scale * (self.rotation @ other.translation) + self.translation,
            self.scale * other.scale,
        )

    def __repr__(self) -> str:
        return (f"Similarity(scale={self.scale:.6g}, reflection={self.is_reflection}, "
                f"translation={np.round(self.translation, 6).tolist()}, "
                f"rotation={np.round(self.rotation, 6).tolist()})")


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of ``[..., 4]`` (w, x, y, z) quaternions: ``R(a * b) = R(a) R(b)``."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def _sh_matrix(world_from_splat: Similarity, degree: int) -> np.ndarray:
    """``[K, K]``: rotate by ``Q``, then band ``l`` times ``(-1)^l`` for a reflection."""
    matrix = sh_rotation_matrix(world_from_splat.proper_rotation, degree)
    if world_from_splat.is_reflection:
        for band in range(1, degree + 1, 2):
            s = band_slice(band)
            matrix[s] *= -1.0
    return matrix


def _check_args(g: Gaussians, world_from_splat: Similarity) -> None:
    if not isinstance(g, Gaussians):
        raise TypeError(f"transform_gaussians: expected Gaussians, got {type(g).__name__}")
    if not isinstance(world_from_splat, Similarity):
        raise TypeError("transform_gaussians: world_from_splat must be a Similarity, "
                        f"got {type(world_from_splat).__name__}")


def transform_gaussians(g: Gaussians, world_from_splat: Similarity) -> Gaussians:
    """The Gaussians ``g`` (splat coordinates) moved into the world frame by ``world_from_splat``.

    Quaternions come back unit (``Q * normalize(q)``; a zero quaternion, read as the identity, becomes ``Q``)."""
    _check_args(g, world_from_splat)
    sim = world_from_splat
    means = sim.apply(g.means)
    q_frame = rotmats_to_quats(sim.proper_rotation[None])[0]
    quats = _quat_multiply(q_frame[None], g.normalized_quats().astype(np.float64))
    log_scales = g.log_scales.astype(np.float64) + np.log(sim.scale)
    degree = g.sh_degree
    if degree == 0:
        sh = g.sh.copy()
    else:
        sh = apply_sh_matrix(_sh_matrix(sim, degree), g.sh)
    return Gaussians.from_arrays(means, quats, log_scales, g.opacity_logits.copy(), sh, dict(g.extras))


def transform_gaussians_reference(g: Gaussians, world_from_splat: Similarity) -> Gaussians:
    """Slow, obvious ``transform_gaussians``: rotation matrices ``Q R_g`` converted back to quaternions, SH by the
    least-squares fit on rotated directions with the full orthogonal matrix (reflection included), float64."""
    _check_args(g, world_from_splat)
    sim = world_from_splat
    means = np.array([sim.scale * sim.rotation @ mu + sim.translation for mu in g.means.astype(np.float64)])
    rotmats = quats_to_rotmats(g.normalized_quats().astype(np.float64))
    quats = rotmats_to_quats(np.array([sim.proper_rotation @ r for r in rotmats]).reshape(-1, 3, 3))
    log_scales = g.log_scales.astype(np.float64) + np.log(sim.scale)
    sh = rotate_sh_reference(g.sh, sim.rotation)
    return Gaussians.from_arrays(means.reshape(-1, 3), quats.reshape(-1, 4), log_scales, g.opacity_logits.copy(),
                                 sh, dict(g.extras))
