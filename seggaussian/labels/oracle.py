"""Oracle Gaussians: flat Gaussians sampled on a labelled mesh (or point cloud), each with its true class.

``--gaussians oracle`` builds datasets without fitting: the Gaussians lie on the labelled surface, so the
label transfer can be scored against the class of the triangle each one was sampled on. Samples are either
area-weighted over all triangles or, with ``OracleConfig.visible_only``, the first hits of rays through
random pixels of the scene's views (open3d raycasting): what a fitted 3DGS can reconstruct.
"""

from __future__ import annotations

import numpy as np

from seggaussian.labels.config import OracleConfig
from seggaussian.core.constants import SH_C0
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.knn import nearest_neighbours

#: Triangles with an area below this (m^2) get no oracle samples (their normal is undefined).
MIN_TRIANGLE_AREA = 1e-12
#: A unit normal within this of -z (1 + n.z below it) is rotated by 180 degrees about x: the half-way
#: quaternion is undefined there.
ANTIPODAL_EPS = 1e-9
#: Floor (metres) of each side of a point cloud's bounding box when deriving oracle scales (flat clouds).
MIN_EXTENT = 1e-3
#: Smallest oracle Gaussian standard deviation (metres): keeps log-scales finite for zero-size samples.
MIN_ORACLE_SCALE = 1e-5
#: Oracle opacities are clipped into [eps, 1 - eps] before the logit (keeps it finite).
OPACITY_EPS = 1e-6
#: Neighbours averaged for the in-plane spacing of sampled oracle Gaussians.
SPACING_NEIGHBOURS = 3


def sample_oracle_gaussians(
    points: np.ndarray,  # [P, 3]
    colors: np.ndarray,  # [P, 3] uint8
    semantic: np.ndarray,  # [P]
    faces: np.ndarray | None,  # [F, 3]
    config: OracleConfig,
    rng: np.random.Generator,
    cameras: tuple = (),
) -> tuple[Gaussians, np.ndarray]:
    """Gaussians sampled on the labelled mesh, flat along the face normal, and their ground-truth class
    ``[N]`` = the label of the sampled triangle's corner with the largest barycentric weight.

    With ``config.visible_only`` and cameras, samples are the first hits of rays through random pixels of
    the views (what a fitted 3DGS can reconstruct; no hidden contact faces such as a shelf's back against
    a wall); otherwise area-weighted over all triangles; on the points themselves for point clouds.
    """
    points = np.asarray(points, np.float64)
    n = int(config.num_gaussians)
    if n <= 0 or not len(points):
        return Gaussians.empty(), np.zeros(0, np.int32)
    faces = None if faces is None or not len(faces) else np.asarray(faces, np.int64)
    areas = cross = None
    if faces is not None:
        a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
        cross = np.cross(b - a, c - a)
        areas = 0.5 * np.linalg.norm(cross, axis=1)
        areas[~(areas > MIN_TRIANGLE_AREA)] = 0.0
        if areas.sum() <= 0:
            faces = None
    if faces is None:
        idx = np.sort(rng.integers(0, len(points), n))
        extent = np.prod(np.maximum(points.max(0) - points.min(0), MIN_EXTENT)) ** (1 / 3)
        sigma = config.scale_factor * extent / max(1.0, n ** (1 / 3))
        return _oracle_gaussians(points[idx], np.asarray(colors, np.float64)[idx] / 255.0,
                                 np.tile([1.0, 0.0, 0.0, 0.0], (len(idx), 1)),
                                 np.full((len(idx), 3), sigma), config), np.asarray(semantic, np.int32)[idx]
    if config.visible_only and len(cameras):
        tri, bary, sigma = _sample_visible(points, faces, cameras, n, rng, config)
    else:
        cdf = np.cumsum(areas)
        tri = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(faces) - 1)
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # [n, 3]
        sigma = np.full(n, config.scale_factor * np.sqrt(areas.sum() / n))
    corners = faces[tri]  # [m, 3]
    means = np.einsum("nk,nkd->nd", bary, points[corners])
    rgb = np.einsum("nk,nkd->nd", bary, np.asarray(colors, np.float64)[corners]) / 255.0
    truth = np.asarray(semantic, np.int32)[corners[np.arange(len(tri)), np.argmax(bary, axis=1)]]
    normals = cross[tri] / np.maximum(2.0 * areas[tri], MIN_TRIANGLE_AREA)[:, None]
    scales = np.stack([sigma, sigma, sigma * config.thickness_ratio], axis=1)
    return _oracle_gaussians(means, rgb, quats_from_z_axis(normals), scales, config), truth


def _oracle_gaussians(means, rgb, quats, scales, config: OracleConfig) -> Gaussians:
    p = np.clip(config.opacity, OPACITY_EPS, 1 - OPACITY_EPS)
    return Gaussians.from_arrays(means, quats, np.log(np.maximum(scales, MIN_ORACLE_SCALE)),
                                 np.full(len(means), np.log(p / (1 - p))), (rgb - 0.5) / SH_C0)


def _sample_visible(points, faces, cameras, n, rng, config: OracleConfig):
    """First hits of ``n`` rays through uniformly random pixels of the cameras (open3d raycasting).

    Returns (triangle ids [m], barycentric weights [m, 3], in-plane sigma [m]); m <= n (misses dropped)."""
    import open3d as o3d

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(points.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(faces.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    per_view = np.diff(np.linspace(0, n, len(cameras) + 1).round().astype(np.int64))
    rays, footprint = [], []
    for cam, m in zip(cameras, per_view):
        uv = rng.random((m, 2)) * [cam.width, cam.height]
        d_cam = np.concatenate([uv, np.ones((m, 1))], axis=1) @ np.linalg.inv(cam.K).T
        c2w = cam.c2w
        d_world = d_cam @ c2w[:3, :3].T
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        rays.append(np.concatenate([np.broadcast_to(c2w[:3, 3], (m, 3)), d_world], axis=1))
        # sample spacing on a fronto-parallel surface at unit depth
        footprint.append(np.full(m, np.sqrt(cam.width * cam.height / max(m, 1)) / cam.K[0, 0]))
    rays = np.concatenate(rays) if rays else np.zeros((0, 6))
    footprint = np.concatenate(footprint) if footprint else np.zeros(0)
    ans = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    hit = np.isfinite(t_hit) & (tri >= 0) & (tri < len(faces))
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    # In-plane size from the realized sample density: every view's samples land on the same surfaces, so a
    # per-view pixel footprint would overestimate the spacing by about sqrt(number of views).
    hit_points = rays[hit, :3] + rays[hit, 3:] * t_hit[hit, None]
    sigma = config.scale_factor * _mean_neighbour_distance(hit_points, fallback=t_hit[hit] * footprint[hit])
    return tri[hit], np.clip(bary[hit], 0.0, 1.0), sigma


def _mean_neighbour_distance(points: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``[m]`` mean distance of each point to its SPACING_NEIGHBOURS nearest others (``fallback`` when too few)."""
    if len(points) <= SPACING_NEIGHBOURS:
        return fallback
    d, _ = nearest_neighbours(points, "scipy")(points, SPACING_NEIGHBOURS + 1)
    spacing = d[:, 1:].mean(axis=1)
    return np.where(spacing > 0, spacing, fallback)


def quats_from_z_axis(normals: np.ndarray) -> np.ndarray:
    """``[N, 4]`` unit quaternions (w, x, y, z) rotating +z onto the (unit) ``normals`` [N, 3]."""
    z = np.array([0.0, 0.0, 1.0])
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), ANTIPODAL_EPS)
    axis = np.cross(np.broadcast_to(z, n.shape), n)
    w = 1.0 + n @ z
    q = np.concatenate([w[:, None], axis], axis=1)
    flip = w < ANTIPODAL_EPS  # normal = -z: rotate 180 degrees about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)
