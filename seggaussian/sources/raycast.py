"""Render a triangle mesh into a pinhole camera by raycasting (open3d ``RaycastingScene``, CPU).

One ray per pixel through the pixel centre (``u + 0.5, v + 0.5``, see ``seggaussian.core.cameras``).
Colour is the barycentric interpolation of the vertex colours at the hit point; labels come from
the hit face; depth is the camera-space z of the hit (0 where the ray misses).

``cast_rays_reference`` is a slow, obviously-correct Moller-Trumbore ray caster kept for tests.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.core.constants import IGNORE_LABEL

#: open3d reports a missed ray with this primitive id (uint32 max).
MISS_PRIMITIVE = 4294967295
#: Ray-triangle determinant below this counts as parallel in the reference caster.
RAY_PARALLEL_EPS = 1e-12


class RayHits(NamedTuple):
    """Per-pixel hits of one view.

    Fields:
        depth: ``[H, W]`` float64 camera z of the hit, 0 where the ray misses.
        face_ids: ``[H, W]`` int64 triangle index, -1 where the ray misses.
        barycentric: ``[H, W, 2]`` float64 (u, v): hit = (1-u-v) a + u b + v c of the face (a, b, c).
    """

    depth: np.ndarray
    face_ids: np.ndarray
    barycentric: np.ndarray


class MeshRender(NamedTuple):
    """An RGB image and the hit record of one view.

    Fields:
        rgb: ``[H, W, 3]`` uint8 (``background`` where the ray misses).
        hits: the ``RayHits`` the image was shaded from.
    """

    rgb: np.ndarray
    hits: RayHits


def compute_pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(origin ``[3]``, directions ``[H, W, 3]``) in world space; each direction has camera z = 1."""
    w, h = camera.width, camera.height
    k = camera.K
    u = (np.arange(w, dtype=np.float64) + 0.5 - k[0, 2]) / k[0, 0]
    v = (np.arange(h, dtype=np.float64) + 0.5 - k[1, 2]) / k[1, 1]
    uu, vv = np.meshgrid(u, v)
    dirs_cam = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    rotation = camera.viewmat[:3, :3]  # world -> camera
    return camera.center, dirs_cam @ rotation  # = (R^T d) row-wise


class MeshRaycaster:
    """A triangle mesh ready to be raycast from many cameras (the BVH is built once)."""

    def __init__(self, points: np.ndarray, faces: np.ndarray):
        import open3d as o3d

        self.points = np.asarray(points, dtype=np.float64)  # [P, 3]
        self.faces = np.asarray(faces, dtype=np.int64)  # [F, 3]
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(self.points.astype(np.float32)),
            o3d.core.Tensor(self.faces.astype(np.uint32)),
        )

    def cast(self, camera: Camera) -> RayHits:
        """Hits of the pixel-centre rays of ``camera``."""
        import open3d as o3d

        origin, dirs = compute_pixel_rays(camera)
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=-1).astype(np.float32)
        result = self._scene.cast_rays(o3d.core.Tensor(rays))  # rays are independent: any thread count gives the same hits
        t_hit = result["t_hit"].numpy().astype(np.float64)
        prim = result["primitive_ids"].numpy().astype(np.int64)
        uvs = result["primitive_uvs"].numpy().astype(np.float64)
        miss = (prim == MISS_PRIMITIVE) | ~np.isfinite(t_hit)
        depth = np.where(miss, 0.0, t_hit)  # direction has camera z = 1, so t is the camera depth
        face_ids = np.where(miss, -1, prim)
        uvs[miss] = 0.0
        return RayHits(depth, face_ids, uvs)

    def first_hits(self, origin: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Along the ray from ``origin [3]`` to each of ``targets [M, 3]``: ``(first [M], distance [M])``, the
        distance (metres, float64) to the first surface hit (inf where the ray hits nothing) and to the target."""
        import open3d as o3d

        origin = np.asarray(origin, np.float64)
        offsets = np.asarray(targets, np.float64) - origin
        distance = np.linalg.norm(offsets, axis=1)
        directions = offsets / np.maximum(distance, 1e-300)[:, None]  # unit: t is then a distance
        rays = np.concatenate([np.broadcast_to(origin, offsets.shape), directions], axis=1).astype(np.float32)
        t_hit = self._scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        return np.where(np.isfinite(t_hit), t_hit, np.inf), distance

    def closest_points(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each of ``points [M, 3]``: ``(triangle [M] int64, uv [M, 2] float64)``, the mesh triangle holding the
        closest point and that point's barycentric ``(u, v)`` (weights ``1 - u - v``, ``u``, ``v`` of its corners)."""
        import open3d as o3d

        answer = self._scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
        return answer["primitive_ids"].numpy().astype(np.int64), answer["primitive_uvs"].numpy().astype(np.float64)

    def render(self, camera: Camera, colors: np.ndarray, background=(0, 0, 0)) -> MeshRender:
        """Barycentric interpolation of vertex ``colors`` ``[P, 3]`` uint8 at each hit."""
        hits = self.cast(camera)
        return MeshRender(shade_hits(hits, self.faces, colors, background), hits)


def shade_hits(hits: RayHits, faces: np.ndarray, colors: np.ndarray, background=(0, 0, 0)) -> np.ndarray:
    """``[H, W, 3]`` uint8 colour from vertex colours interpolated with the hit barycentrics."""
    hit = hits.face_ids >= 0
    out = np.empty(hits.face_ids.shape + (3,), dtype=np.uint8)
    out[:] = np.asarray(background, dtype=np.uint8)
    tri = faces[hits.face_ids[hit]]  # [n, 3]
    uv = hits.barycentric[hit].astype(np.float32)  # [n, 2]
    weights = np.concatenate([1.0 - uv.sum(axis=1, keepdims=True), uv], axis=1)  # [n, 3]
    corner_colors = colors.astype(np.float32)[tri]  # [n, 3 corners, 3 channels]
    mixed = np.einsum("nk,nkc->nc", weights, corner_colors)
    out[hit] = np.clip(np.round(mixed), 0, 255).astype(np.uint8)
    return out


def label_image(hits: RayHits, face_labels: np.ndarray, ignore: int) -> np.ndarray:
    """``[H, W]`` label of the hit face (``ignore`` where the ray misses)."""
    out = np.full(hits.face_ids.shape, ignore, dtype=np.int64)
    hit = hits.face_ids >= 0
    out[hit] = np.asarray(face_labels)[hits.face_ids[hit]]
    return out


def cast_rays_reference(points: np.ndarray, faces: np.ndarray, camera: Camera) -> RayHits:
    """Slow Moller-Trumbore reference: every pixel against every triangle (tiny meshes only)."""
    origin, dirs = compute_pixel_rays(camera)
    h, w = dirs.shape[:2]
    depth = np.zeros((h, w))
    face_ids = np.full((h, w), -1, dtype=np.int64)
    bary = np.zeros((h, w, 2))
    a, b, c = (np.asarray(points, np.float64)[faces[:, i]] for i in range(3))
    e1, e2 = b - a, c - a
    for y in range(h):
        for x in range(w):
            d = dirs[y, x]
            best = np.inf
            for f in range(len(faces)):
                p = np.cross(d, e2[f])
                det = e1[f] @ p
                if abs(det) < RAY_PARALLEL_EPS:
                    continue
                s = origin - a[f]
                u = (s @ p) / det
                q = np.cross(s, e1[f])
                v = (d @ q) / det
                t = (e2[f] @ q) / det
                if u < 0 or v < 0 or u + v > 1 or t <= 0 or t >= best:
                    continue
                best, face_ids[y, x], bary[y, x] = t, f, (u, v)
            if np.isfinite(best):
                depth[y, x] = best
    return RayHits(depth, face_ids, bary)


class LabelledRender(NamedTuple):
    """One rendered view with ground truth.

    Fields:
        rgb: ``[H, W, 3]`` uint8.
        semantic: ``[H, W]`` int64 class id of the hit face (IGNORE_LABEL where void or missed).
        instance: ``[H, W]`` int64 instance id of the hit face (IGNORE_LABEL where void or missed).
        depth: ``[H, W]`` float64 camera z (0 where missed).
    """

    rgb: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    depth: np.ndarray


def render_labelled_views(
    points: np.ndarray,  # [P, 3]
    faces: np.ndarray,  # [F, 3]
    colors: np.ndarray,  # [P, 3] uint8
    face_semantic: np.ndarray,  # [F]
    face_instance: np.ndarray,  # [F]
    cameras: list[Camera],
):
    """Yield a ``LabelledRender`` per camera (the BVH is built once)."""
    caster = MeshRaycaster(points, faces)
    for camera in cameras:
        hits = caster.cast(camera)
        yield LabelledRender(
            shade_hits(hits, caster.faces, colors),
            label_image(hits, face_semantic, IGNORE_LABEL),
            label_image(hits, face_instance, IGNORE_LABEL),
            hits.depth,
        )
