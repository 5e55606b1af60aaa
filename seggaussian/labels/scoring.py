"""Scoring transferred labels against the mesh: each Gaussian's ground-truth class from the closest triangle,
and the per-scene label accuracy (reported by the build, never used to produce labels).
"""

from __future__ import annotations

import numpy as np

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.knn import nearest_neighbours


def surface_labels(
    query_points: np.ndarray,  # [Q, 3]
    vertices: np.ndarray,  # [P, 3]
    faces: np.ndarray | None,  # [F, 3]
    semantic: np.ndarray,  # [P]
) -> np.ndarray:
    """Ground-truth class of each query point: the label of the vertex with the largest barycentric
    weight on the closest mesh triangle (open3d raycasting scene); nearest vertex for point clouds.

    Used to score transferred labels of fitted Gaussians (``label_accuracy``), never to produce them.
    """
    query_points = np.asarray(query_points, np.float64)
    if not len(query_points):
        return np.zeros(0, np.int32)
    if faces is None or not len(faces):
        _, i = nearest_neighbours(vertices, "scipy")(query_points, 1)
        return np.asarray(semantic, np.int32)[i[:, 0]]
    import open3d as o3d

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(np.asarray(vertices, np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.asarray(faces, np.int32))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(mesh)
    ans = rc.compute_closest_points(o3d.core.Tensor(query_points.astype(np.float32)))
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    corner = np.argmax(bary, axis=1)
    vertex = np.asarray(faces, np.int64)[tri, corner]
    return np.asarray(semantic, np.int32)[vertex]


def label_accuracy(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """Share of Gaussians whose transferred class equals the ground truth, over those with a labelled
    ground truth (a transferred IGNORE counts as wrong). ``accuracy`` is None when nothing is scorable."""
    scored = truth != IGNORE_LABEL
    n = int(scored.sum())
    correct = int((predicted[scored] == truth[scored]).sum())
    return {"scored": n, "correct": correct, "accuracy": (correct / n) if n else None}
