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

Occluded points give no label across the gate, but a Gaussian that lies *on* a surface no view sees (a scan turned
into splats has one at every vertex, the floor under a box included) keeps that surface's label
(``on_hidden_surface``): its closest point on the mesh is within ``on_surface_tolerance`` and is itself occluded.
It then takes the labels of the vertex with the largest barycentric weight on that closest triangle, the rule the
mesh samples follow (``seggaussian.labels.transfer.densify_labelled_mesh``), so an unlabelled surface stays ignore.
``on_hidden_surface`` asks open3d for the closest points; ``on_hidden_surface_reference`` measures every Gaussian
against every triangle (float64; tiny meshes only).
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.labels.config import DEFAULT_ON_SURFACE_TOLERANCE
from seggaussian.labels.transfer import HiddenSurfaceHits
from seggaussian.sources.raycast import RAY_PARALLEL_EPS, MeshRaycaster

#: Default of ``TransferConfig.occlusion_tolerance`` (metres): half the 2 cm between the synthetic rooms' windows and
#: the wall behind them, and more than float32 ray casting's error at room scale (about 1e-6 m per metre).
DEFAULT_OCCLUSION_TOLERANCE = 0.01
#: Points nearer a camera centre than this (metres) count as behind it (outside its image).
NEAR_PLANE = 1e-3
#: Metres added to a cube's bounding sphere in ``PointCells``' view test: room for rounding, never for a point.
CELL_MARGIN = 1e-3
#: Triangles whose doubled area is below this (square metres) have no usable barycentric frame in the reference's
#: closest-point search; only their corners and edges are measured there.
DEGENERATE_TRIANGLE_AREA = 1e-18


def points_in_image(points: np.ndarray, camera: Camera) -> np.ndarray:  # [P, 3] -> [P] bool
    """Points in front of ``camera`` (camera z > ``NEAR_PLANE``) that project inside its image (pixel edges at 0 and
    width/height). The arithmetic is written out element by element in a fixed order (camera coordinates
    ``R[r, 0] x + R[r, 1] y + R[r, 2] z + t[r]``, then ``u = (K[0] . p) / z``, ``v = (K[1] . p) / z``), the order the
    compiled test of ``PointCells.rows_in_image`` follows, so that both accept the same points to the bit."""
    points = np.asarray(points, np.float64)
    rotation, translation, K = camera.viewmat[:3, :3], camera.viewmat[:3, 3], camera.K
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    cam = [rotation[r, 0] * x + rotation[r, 1] * y + rotation[r, 2] * z + translation[r] for r in range(3)]
    front = cam[2] > NEAR_PLANE
    depth = np.where(front, cam[2], 1.0)  # behind the camera: outside, whatever the division gave
    u = (K[0, 0] * cam[0] + K[0, 1] * cam[1] + K[0, 2] * cam[2]) / depth
    v = (K[1, 0] * cam[0] + K[1, 1] * cam[1] + K[1, 2] * cam[2]) / depth
    return front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


@numba.njit(cache=True, nogil=True)
def _rows_in_image(points, order, cell_start, cell_kept, skip, rotation, translation, K, width, height, near, out):
    """Into ``out``: the rows ``order[cell_start[c]:cell_start[c + 1]]`` of every kept cell ``c`` that ``skip`` does
    not mark and that :func:`points_in_image` accepts (its arithmetic, in its order); returns how many."""
    n = 0
    for c in range(cell_kept.shape[0]):
        if not cell_kept[c]:
            continue
        for j in range(cell_start[c], cell_start[c + 1]):
            i = order[j]
            if skip[i]:
                continue
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            cx = rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2] * z + translation[0]
            cy = rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2] * z + translation[1]
            cz = rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2] * z + translation[2]
            if not cz > near:
                continue
            u = (K[0, 0] * cx + K[0, 1] * cy + K[0, 2] * cz) / cz
            v = (K[1, 0] * cx + K[1, 1] * cy + K[1, 2] * cz) / cz
            if u >= 0 and u < width and v >= 0 and v < height:
                out[n] = i
                n += 1
    return n


class PointCells:
    """Points bucketed in cubes of ``cell_size`` metres, for a quick conservative view test: a camera's
    ``maybe_in_image`` cubes hold every point ``points_in_image`` accepts (and others), so the exact projection runs
    only on their points, not on every point for every camera.

    A cube may hold a point in the image only if its bounding sphere (radius ``cell_size * sqrt(3) / 2``, plus
    ``CELL_MARGIN``) reaches the positive side of each of the five planes ``points_in_image`` tests in camera
    coordinates: z > ``NEAR_PLANE``, K[0].p >= 0, (width e_z - K[0]).p > 0, K[1].p >= 0, (height e_z - K[1]).p > 0
    (u = K[0].p / z, v = K[1].p / z). The margin is far above the rounding of either test (1e-12 m at room scale).
    """

    def __init__(self, points: np.ndarray, cell_size: float = 0.25):
        points = np.asarray(points, np.float64)
        self.cell_size = float(cell_size)
        self.radius = self.cell_size * np.sqrt(3.0) / 2.0 + CELL_MARGIN
        if not len(points):
            self.cell_of_point, self.centres = np.zeros(0, np.int64), np.zeros((0, 3))
            self._points, self._order, self._cell_start = np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(1, np.int64)
            return
        low = points.min(axis=0)
        ijk = np.floor((points - low) / self.cell_size).astype(np.int64)
        span = ijk.max(axis=0) + 1
        keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
        unique, self.cell_of_point = np.unique(keys, return_inverse=True)
        cells = np.stack([unique // (span[1] * span[2]), (unique // span[2]) % span[1], unique % span[2]], axis=1)
        self.centres = low + (cells + 0.5) * self.cell_size
        self._points = np.ascontiguousarray(points)
        self._order = np.argsort(self.cell_of_point, kind="stable")  # the points cell by cell
        self._cell_start = np.searchsorted(self.cell_of_point[self._order], np.arange(len(unique) + 1))

    def maybe_in_image(self, camera: Camera) -> np.ndarray:  # [C] bool
        """Cubes that may hold a point ``points_in_image(.., camera)`` accepts."""
        rotation, translation = camera.viewmat[:3, :3], camera.viewmat[:3, 3]
        k0, k1, ez = camera.K[0], camera.K[1], np.array([0.0, 0.0, 1.0])
        normals = np.stack([ez, k0, camera.width * ez - k0, k1, camera.height * ez - k1])  # camera coordinates
        offsets = np.array([-NEAR_PLANE, 0.0, 0.0, 0.0, 0.0])
        world = normals @ rotation  # n . (R x + t) = (R^T n) . x + n . t
        signed = self.centres @ world.T + (normals @ translation + offsets)
        reach = self.radius * np.linalg.norm(world, axis=1)
        return (signed >= -reach).all(axis=1)

    def rows_in_image(self, camera: Camera, skip: np.ndarray) -> np.ndarray:  # [P] bool -> [M] int64
        """The rows of the points ``points_in_image(.., camera)`` accepts, less those ``skip`` marks, found among the
        points of the ``maybe_in_image`` cubes only (compiled; cube by cube, so the rows are not sorted)."""
        out = np.empty(len(self._order), np.int64)
        count = _rows_in_image(self._points, self._order, self._cell_start, self.maybe_in_image(camera),
                               np.ascontiguousarray(skip, np.bool_), np.ascontiguousarray(camera.viewmat[:3, :3]),
                               np.ascontiguousarray(camera.viewmat[:3, 3]), np.ascontiguousarray(camera.K),
                               float(camera.width), float(camera.height), NEAR_PLANE, out)
        return out[:count]


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
    caster: MeshRaycaster | None = None,
) -> np.ndarray:  # [P] bool
    """``[P]`` True where the point is occluded (module docstring) by the mesh ``(mesh_points, faces)``; ``caster``:
    that mesh's raycaster when the caller has one (its BVH is built once per mesh)."""
    mesh_points, faces, points = _check(mesh_points, faces, points, tolerance)
    looked_at = np.zeros(len(points), bool)
    seen = np.zeros(len(points), bool)
    if not len(points) or not len(faces):
        return seen  # nothing to test, or nothing that could hide a point
    caster = caster if caster is not None else MeshRaycaster(mesh_points, faces)
    cells = PointCells(points)
    for camera in cameras:
        # A point seen once stays seen (and was looked at), so each camera projects only the points not yet seen, and
        # of those only the ones in cubes that may lie in its view (``PointCells``: the same rows as all of them).
        rows = cells.rows_in_image(camera, seen)
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


def _check_means(means: np.ndarray, on_surface_tolerance: float) -> np.ndarray:
    """Gaussian centres as float64 ``[N, 3]`` (NaN/Inf rows allowed: such a Gaussian lies on nothing)."""
    means = np.asarray(means, np.float64)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"occlusion: gaussian means must be [N, 3], got {means.shape}")
    if not (np.isfinite(on_surface_tolerance) and on_surface_tolerance >= 0):
        raise ValueError(f"occlusion: on_surface_tolerance must be a finite number >= 0, got {on_surface_tolerance}")
    return means


def _hits(rows, tri, bary, distance, faces, occluded) -> HiddenSurfaceHits:
    """Of the Gaussians ``rows`` near the mesh, those whose closest point is ``occluded``, with the vertex of the
    largest barycentric weight ``bary`` on their closest triangle ``tri``."""
    vertex = faces[tri[occluded], np.argmax(bary[occluded], axis=1)]
    return HiddenSurfaceHits(rows[occluded].astype(np.int64), vertex.astype(np.int64),
                             distance[occluded].astype(np.float32))


def _no_hits() -> HiddenSurfaceHits:
    return HiddenSurfaceHits(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))


def on_hidden_surface(
    means: np.ndarray,  # [N, 3] Gaussian centres
    mesh_points: np.ndarray,  # [V, 3]
    faces: np.ndarray,  # [F, 3]
    cameras: Sequence[Camera],
    tolerance: float = DEFAULT_OCCLUSION_TOLERANCE,
    on_surface_tolerance: float = DEFAULT_ON_SURFACE_TOLERANCE,
    caster: MeshRaycaster | None = None,
) -> HiddenSurfaceHits:
    """The Gaussians whose closest point on the mesh is within ``on_surface_tolerance`` and occluded
    (``occluded_points`` with ``tolerance``): they lie on a surface the views never see (module docstring).
    ``caster``: the mesh's raycaster when the caller has one (one BVH for the closest points and the rays)."""
    mesh_points, faces, _ = _check(mesh_points, faces, np.zeros((0, 3)), tolerance)
    means = _check_means(means, on_surface_tolerance)
    if not len(means) or not len(faces) or not len(cameras):
        return _no_hits()
    caster = caster if caster is not None else MeshRaycaster(mesh_points, faces)
    finite = np.flatnonzero(np.isfinite(means).all(axis=1))
    # the closest point again in float64 from its triangle and barycentrics, so that distances are exact to float32's
    # barycentrics and not to float32 coordinates far from the origin
    tri, uv = caster.closest_points(means[finite])
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    closest = np.einsum("nk,nkd->nd", bary, mesh_points[faces[tri]])
    distance = np.linalg.norm(means[finite] - closest, axis=1)
    near = np.flatnonzero(distance <= on_surface_tolerance)
    if not len(near):
        return _no_hits()
    occluded = occluded_points(mesh_points, faces, closest[near], cameras, tolerance, caster)
    return _hits(finite[near], tri[near], bary[near], distance[near], faces, occluded)


def closest_points_on_triangles_reference(point: np.ndarray, a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """For one ``point [3]`` and triangles ``(a, b, c)`` (``[F, 3]`` each): ``(closest [F, 3], barycentric [F, 3])``,
    the closest point of each triangle and its barycentric weights, by brute force: the interior projection when it
    falls inside, otherwise the best of the three edges (each clamped to its segment)."""
    candidates, weights = [], []
    n = np.cross(b - a, c - a)
    area2 = np.einsum("fk,fk->f", n, n)
    ok = area2 > DEGENERATE_TRIANGLE_AREA
    safe = np.where(ok, area2, 1.0)
    # barycentrics of the projection onto the plane (signed sub-areas over the whole)
    wa = np.einsum("fk,fk->f", np.cross(b - point, c - point), n) / safe
    wb = np.einsum("fk,fk->f", np.cross(c - point, a - point), n) / safe
    wc = 1.0 - wa - wb
    inside = ok & (wa >= 0) & (wb >= 0) & (wc >= 0)
    w = np.stack([wa, wb, wc], axis=1)
    candidates.append(np.where(inside[:, None], w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c, np.inf))
    weights.append(w)
    for (p, q, i, j) in ((a, b, 0, 1), (b, c, 1, 2), (c, a, 2, 0)):
        e = q - p
        length2 = np.einsum("fk,fk->f", e, e)
        t = np.clip(np.einsum("fk,fk->f", point - p, e) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        t = np.where(length2 > 0, t, 0.0)
        edge_w = np.zeros((len(a), 3))
        edge_w[:, i], edge_w[:, j] = 1.0 - t, t
        candidates.append(p + t[:, None] * e)
        weights.append(edge_w)
    candidates, weights = np.stack(candidates), np.stack(weights)  # [4, F, 3]
    d = np.linalg.norm(candidates - point, axis=2)  # inf for an interior projection outside its triangle
    best = np.argmin(d, axis=0)
    pick = np.arange(len(a))
    return candidates[best, pick], weights[best, pick]


def on_hidden_surface_reference(means, mesh_points, faces, cameras, tolerance=DEFAULT_OCCLUSION_TOLERANCE,
                                on_surface_tolerance=DEFAULT_ON_SURFACE_TOLERANCE) -> HiddenSurfaceHits:
    """:func:`on_hidden_surface`, every Gaussian against every triangle (float64), the occlusion by
    :func:`occluded_points_reference`."""
    mesh_points, faces, _ = _check(mesh_points, faces, np.zeros((0, 3)), tolerance)
    means = _check_means(means, on_surface_tolerance)
    if not len(means) or not len(faces) or not len(cameras):
        return _no_hits()
    a, b, c = (mesh_points[faces[:, i]] for i in range(3))
    rows, closest, tri, bary, distance = [], [], [], [], []
    for row, mean in enumerate(means):
        if not np.isfinite(mean).all():
            continue
        points, weights = closest_points_on_triangles_reference(mean, a, b, c)
        d = np.linalg.norm(points - mean, axis=1)
        best = int(np.argmin(d))
        if d[best] <= on_surface_tolerance:
            rows.append(row), closest.append(points[best]), tri.append(best), bary.append(weights[best])
            distance.append(d[best])
    if not rows:
        return _no_hits()
    closest = np.array(closest)
    occluded = occluded_points_reference(mesh_points, faces, closest, cameras, tolerance)
    return _hits(np.array(rows), np.array(tri), np.array(bary), np.array(distance), faces, occluded)


__all__ = ["DEFAULT_OCCLUSION_TOLERANCE", "DEFAULT_ON_SURFACE_TOLERANCE", "HiddenSurfaceHits",
           "closest_points_on_triangles_reference", "occluded_points", "occluded_points_reference",
           "on_hidden_surface", "on_hidden_surface_reference", "points_in_image"]
