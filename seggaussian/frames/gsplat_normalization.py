"""gsplat ``simple_trainer``'s world normalization (``normalize_world_space=True``, the default), recomputed.

gsplat's ``examples/datasets/colmap.py`` ``Parser(normalize=True)`` moves the COLMAP world (camera poses and 3D
points) into a normalized frame before training, and the trained PLY's means live in that frame. The steps
(``examples/datasets/normalize.py``, gsplat 1.0 .. 1.5.x, verified against the repository):

1. ``T1 = similarity_from_cameras(camtoworlds)`` (``strict_scaling=False``, ``center_method="focus"``):
   - up: ``world_up`` = normalized mean of the cameras' up axes (``-y`` camera column of each camera-to-world);
     ``R_align`` = Rodrigues rotation taking ``world_up`` onto ``(0, -1, 0)`` (``I + K + K^2 / (1 + c)`` with
     ``K = [world_up x (0,-1,0)]_x``, ``c = world_up . (0,-1,0)``) when ``c > -1``, else ``diag(-1, 1, 1)``;
   - centre: each camera's optical axis (``+z`` camera column, after ``R_align``) gives the point nearest to the
     origin, ``t + ((f . -t) f)``; ``translate = -median`` of those points (per coordinate);
   - scale: ``s = 1 / median |t + translate|`` over the rotated camera centres ``t``;
   - ``T1 = [[s R_align, s translate], [0 0 0 1]]``.
2. ``T2 = align_principal_axes(T1 points)``: centroid = per-coordinate median of the points; eigenvectors of
   ``np.cov`` of the centred points (``np.linalg.eigh``), sorted by decreasing eigenvalue (``z`` = the smallest
   spread); the first column negated if the determinant is negative; ``T2 = [[E^T, -E^T centroid], [0 0 0 1]]``.
3. gsplat >= 1.5.2 only (``Fix for up side down``, PR #648): when ``median(z) > mean(z)`` of the points after
   ``T2``, ``T3 = diag(1, -1, -1, 1)`` (180 degrees about x).

The normalization is ``T3 T2 T1`` (``T2 T1`` before 1.5.2). gsplat casts the COLMAP points to float32 before the
steps; so does this module. Eigenvector signs are those of ``np.linalg.eigh`` (LAPACK), as in gsplat.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The gsplat release that added the upside-down flip (T3).
GSPLAT_FLIP_VERSION = "1.5.2"


class GsplatNormalizationError(ValueError):
    """The COLMAP model cannot be normalized the way gsplat does (too few cameras or points, degenerate)."""


@dataclass(frozen=True, eq=False)
class GsplatNormalization:
    """The steps' matrices (``[4, 4]`` float64) and what decided them.

    Fields:
        t1, t2, t3: the three steps (``t3`` the identity when no flip was applied or asked for).
        transform: ``t3 @ t2 @ t1``, normalized-from-COLMAP-world.
        scale: the scale of ``t1``.
        flipped: whether ``t3`` flipped the scene.
    """

    t1: np.ndarray
    t2: np.ndarray
    t3: np.ndarray
    transform: np.ndarray
    scale: float
    flipped: bool


def similarity_from_cameras(camtoworlds: np.ndarray) -> tuple[np.ndarray, float]:
    """gsplat's step 1 (defaults ``strict_scaling=False``, ``center_method="focus"``): (``T1`` [4, 4], scale)."""
    c2w = np.asarray(camtoworlds, dtype=np.float64)
    centres, rotations = c2w[:, :3, 3], c2w[:, :3, :3]
    world_up = np.mean(-rotations[:, :, 1], axis=0)
    norm = np.linalg.norm(world_up)
    if not norm > 0.0:
        raise GsplatNormalizationError("the cameras' up axes cancel out: no mean up direction")
    world_up = world_up / norm
    up_camspace = np.array([0.0, -1.0, 0.0])
    c = float(up_camspace @ world_up)
    axis = np.cross(world_up, up_camspace)
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    if c > -1.0:
        r_align = np.eye(3) + skew + (skew @ skew) / (1.0 + c)
    else:  # gsplat's branch for a world whose up is exactly +y
        r_align = np.diag([-1.0, 1.0, 1.0])
    forwards = (r_align @ rotations)[:, :, 2]
    centres = centres @ r_align.T
    nearest = centres + np.sum(forwards * -centres, axis=-1)[:, None] * forwards
    translate = -np.median(nearest, axis=0)
    distance = float(np.median(np.linalg.norm(centres + translate, axis=-1)))
    if not (np.isfinite(distance) and distance > 0.0):
        raise GsplatNormalizationError(f"median camera distance to the focus point is {distance}: cannot scale")
    scale = 1.0 / distance
    t1 = np.eye(4)
    t1[:3, :3] = scale * r_align
    t1[:3, 3] = scale * translate
    return t1, scale


def align_principal_axes(points: np.ndarray) -> np.ndarray:
    """gsplat's step 2: ``T2`` [4, 4], a rotation (det +1) about the points' median onto their principal axes."""
    p = np.asarray(points, dtype=np.float64)
    centroid = np.median(p, axis=0)
    covariance = np.cov(p - centroid, rowvar=False)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    eigenvectors = eigenvectors[:, eigenvalues.argsort()[::-1]]
    if np.linalg.det(eigenvectors) < 0:
        eigenvectors[:, 0] *= -1.0
    rotation = eigenvectors.T
    t2 = np.eye(4)
    t2[:3, :3] = rotation
    t2[:3, 3] = -rotation @ centroid
    return t2


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def gsplat_normalization(camtoworlds: np.ndarray, points: np.ndarray, *, upside_down_fix: bool = True
                         ) -> GsplatNormalization:
    """The normalization gsplat's COLMAP parser applies: ``camtoworlds`` ``[N, 4, 4]`` (OpenCV, COLMAP world),
    ``points`` ``[P, 3]`` (COLMAP world). ``upside_down_fix``: gsplat >= 1.5.2 (True) or 1.0 .. 1.5.1 (False)."""
    c2w = np.asarray(camtoworlds, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) == 0:
        raise GsplatNormalizationError(f"expected [N>=1, 4, 4] camera poses, got shape {c2w.shape}")
    # gsplat reads the points as float32 (``dtype=np.float32``) and transforms them in float64
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3).astype(np.float32).astype(np.float64)
    if len(pts) < 2:
        raise GsplatNormalizationError(f"{len(pts)} 3D points: gsplat's principal-axes step needs at least 2")
    t1, scale = similarity_from_cameras(c2w)
    pts = _apply(t1, pts)
    t2 = align_principal_axes(pts)
    pts = _apply(t2, pts)
    flipped = bool(upside_down_fix and np.median(pts[:, 2]) > np.mean(pts[:, 2]))
    t3 = np.diag([1.0, -1.0, -1.0, 1.0]) if flipped else np.eye(4)
    transform = t3 @ t2 @ t1
    if not np.isfinite(transform).all():
        raise GsplatNormalizationError("the normalization is not finite (degenerate cameras or points)")
    return GsplatNormalization(t1, t2, t3, transform, scale, flipped)
