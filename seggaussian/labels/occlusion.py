"""Occluded label points: points of a mesh that the scene's cameras look at but never see.

A synthetic or scanned mesh can hold surfaces no image shows: the wall behind a window or a door set 2 cm in front
of it, the floor under a box, the back of a shelf against a wall. A 3DGS fitted to the images has Gaussians only on
what the images show, so such a surface must not give its label to them: a Gaussian on a window, a centimetre off
the glass, is nearer the hidden wall's points than the window's about as often as not, and the nearest-point
transfer then labels it wall (measured on the synthetic rooms: benchmarks/results/build.md, "Occlusion test").

Definition (``occluded_points``): a point is **occluded** when it lies in front of at least one camera and inside
its image, and, for every such camera, the first surface along the ray from the camera centre to the point is
nearer than the point by more than ``tolerance`` metres. A point no camera looks at is *not* occluded: nothing is
known about it, and it keeps its label (a fit initialised from the scan may leave Gaussians there).

``occluded_points`` casts the rays with open3d's BVH (``seggaussian.sources.raycast.MeshRaycaster.first_hits``);
``occluded_points_reference`` tests every ray against every triangle (Moller-Trumbore; tiny meshes only).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.sources.raycast import RAY_PARALLEL_EPS, MeshRaycaster

#: Default of ``TransferConfig.occlusion_tolerance`` (metres): half the 2 cm between the synthetic rooms' windows and
#: the wall behind them, and more than float32 ray casting's error at room scale (about 1e-6 m per metre).
DEFAULT_OCCLUSION_TOLERANCE = 0.01
#: Points nearer a camera centre than this (metres) count as behind it (outside its image).
NEAR_PLANE = 1e-3


def points_in_image(points: np.ndarray, camera: Camera) -> np.ndarray:  # [P, 3] -> [P] bool
    """Points in front of ``camera`` (camera z > ``NEAR_PLANE``) that project inside its image (``Camera.project``,
    pixel edges at 0 and width/height)."""
    uv, z = camera.project(points)
    front = z > NEAR_PLANE
    uv = np.where(front[:, None], uv, -1.0)  # behind the camera: outside, whatever the division gave
    return front & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)


def _checked_points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"occlusion: {name} must be [P, 3], got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"occlusion: {name} hold NaN or Inf")
    return points


def _check(mesh_points, faces, points, tolerance) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inputs of :func:`occluded_points` as float64 / int64 arrays, or a one-line ``ValueError``."""
    mesh_points, points = _checked_points(mesh_points, "mesh points"), _checked_points(points, "points")
    faces = np.asarray(faces, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"occlusion: faces must be [F, 3], got {faces.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(mesh_points)):
        raise ValueError(f"occlusion: faces index vertices outside 0..{len(mesh_points) - 1}")
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"occlusion: tolerance must be a finite number >= 0, got {tolerance}")
    return mesh_points, faces, points


def occluded_points(
    mesh_points: np.ndarray,  # [V, 3] vertices of the occluding mesh
    faces: np.ndarray,  # [F, 3]
    points: np.ndarray,  # [P, 3] the points to test (vertices, samples on the faces, ...)
    cameras: Sequence[Camera],
    tolerance: float = DEFAULT_OCCLUSION_TOLERANCE,
) -> np.ndarray:  # [P] bool
    """``[P]`` True where the point is occluded (module docstring) by the mesh ``(mesh_points, faces)``."""
    mesh_points, faces, points = _check(mesh_points, faces, points, tolerance)
    looked_at = np.zeros(len(points), bool)
    seen = np.zeros(len(points), bool)
    if not len(points) or not len(faces):
        return seen  # nothing to test, or nothing that could hide a point
    caster = MeshRaycaster(mesh_points, faces)
    for camera in cameras:
        # A point seen once stays seen (and was looked at), so each camera projects only the points not yet seen.
        unseen = np.flatnonzero(~seen)
        rows = unseen[points_in_image(points[unseen], camera)]
        looked_at[rows] = True
        if len(rows):
            first, distance = caster.first_hits(camera.center, points[rows])
            seen[rows] = first >= distance - tolerance
    return looked_at & ~seen


def _first_hit_reference(origin, direction, a, e1, e2) -> float:
    """Distance along the unit ``direction`` from ``origin`` to the nearest of the triangles ``(a, a + e1, a + e2)``
    (``[F, 3]`` each), inf if none: Moller-Trumbore's ``t = e2 . q / det`` with barycentric ``(u, v)`` inside the
    triangle, every triangle at once."""
    p = np.cross(direction, e2)
    det = np.einsum("fk,fk->f", e1, p)
    usable = np.abs(det) >= RAY_PARALLEL_EPS
    det = np.where(usable, det, 1.0)
    s = origin - a
    q = np.cross(s, e1)
    u = np.einsum("fk,fk->f", s, p) / det
    v = (q @ direction) / det
    t = np.einsum("fk,fk->f", e2, q) / det
    hit = usable & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return float(t[hit].min()) if hit.any() else np.inf


def occluded_points_reference(mesh_points, faces, points, cameras, tolerance=DEFAULT_OCCLUSION_TOLERANCE):
    """:func:`occluded_points`, every camera-to-point ray against every triangle (Moller-Trumbore, float64)."""
    mesh_points, faces, points = _check(mesh_points, faces, points, tolerance)
    a, b, c = (mesh_points[faces[:, i]] for i in range(3))
    e1, e2 = b - a, c - a
    out = np.zeros(len(points), bool)
    for row, point in enumerate(points):
        looked_at, seen = False, False
        for camera in cameras:
            if not points_in_image(point[None], camera)[0]:
                continue
            looked_at = True
            origin = np.asarray(camera.center, np.float64)
            distance = float(np.linalg.norm(point - origin))
            direction = (point - origin) / distance
            first = _first_hit_reference(origin, direction, a, e1, e2)
            if first >= distance - tolerance:
                seen = True
                break
        out[row] = looked_at and not seen
    return out


__all__ = ["DEFAULT_OCCLUSION_TOLERANCE", "occluded_points", "occluded_points_reference", "points_in_image"]
