"""Where the network places a splat's Gaussians: their centres moved onto the splat's own surface.

A photometric fit without depth leaves a room's Gaussians in thick shells about its surfaces (a default-preset CPU fit:
about a fifth 5 cm or more off the mesh, along the normal, on both sides), where a depth-supervised fit, a scan or
oracle Gaussians lie on them. The voxels such a shell occupies are what a network trained on thin surfaces misreads
(benchmarks/results/renditions.md). :func:`surface_positions` is a moving-least-squares projection with a metric
reach (``OVGaussianNetConfig.surface_radius``): each centre moves along the normal of the opacity-weighted plane of
the splat around it onto that plane, twice. It needs no mesh, cameras or image, and the neighbourhood is measured in
metres through support points (opacity-weighted centroids of ``SURFACE_CELL`` cells), so the plane does not depend on
how many Gaussians the splat spends on a surface. Only the positions the network voxelizes move; every Gaussian keeps
its row, attributes, label and its own place in the blend weights.

:func:`surface_positions_reference` is the same projection written point by point (the slow, obviously-correct form).
"""

from __future__ import annotations

import numpy as np

#: Edge (metres) of the cells whose opacity-weighted centroids are the planes' support points.
SURFACE_CELL = 0.03
#: Projections in a row (the second pulls in what the first left of a thick shell).
SURFACE_ITERATIONS = 2
#: At most this many nearest support points inside the radius make a plane.
SURFACE_NEIGHBOURS = 64
#: A plane needs at least this many support points inside the radius; a centre with fewer stays where it is.
SURFACE_MIN_SUPPORT = 4
#: A support point's weight: its opacity sum times ``exp(-(d / (SURFACE_KERNEL * radius))^2)``.
SURFACE_KERNEL = 0.5


def _supports(means: np.ndarray, opacity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(support points [S, 3], their opacity sums [S], each centre's cell [N])``."""
    cells = np.floor(means / SURFACE_CELL).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:  # one int64 key a cell, in the rows' order
        keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
        _, cell_of = np.unique(keys, return_inverse=True)
    else:
        _, cell_of = np.unique(cells, axis=0, return_inverse=True)
    cell_of = cell_of.reshape(-1)
    mass = np.bincount(cell_of, weights=opacity)
    points = np.stack([np.bincount(cell_of, weights=opacity * means[:, j]) for j in range(3)], axis=1)
    return points / np.maximum(mass, 1e-300)[:, None], mass, cell_of


def weighted_plane(points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted centroid ``[..., 3]`` and unit normal ``[..., 3]`` (least-spread axis, sign arbitrary) of
    ``points [..., K, 3]`` with ``weights [..., K]`` (the off-surface augment's normals use it with weights 1)."""
    total = np.maximum(weights.sum(axis=-1, keepdims=True), 1e-300)
    centroid = (weights[..., None] * points).sum(axis=-2) / total
    offsets = points - centroid[..., None, :]
    covariance = np.einsum("...k,...ki,...kj->...ij", weights, offsets, offsets)
    _, vectors = np.linalg.eigh(covariance)
    return centroid, vectors[..., :, 0]


def surface_positions(means: np.ndarray,  # [N, 3] metres
                      opacity: np.ndarray,  # [N] in [0, 1]
                      radius: float) -> np.ndarray:  # [N, 3] float64
    """The centres moved onto the splat's surface (module docstring): per iteration, every support point's plane
    from the support points within ``radius`` (kernel-weighted by distance, weighted by opacity), and every centre
    projected onto its cell's plane. ``radius <= 0`` returns the centres unchanged."""
    moved = np.asarray(means, dtype=np.float64).reshape(-1, 3).copy()
    weight = np.clip(np.asarray(opacity, dtype=np.float64).reshape(-1), 0.0, 1.0)
    if radius <= 0.0 or len(moved) == 0:
        return moved
    import torch
    from scipy.spatial import cKDTree

    for _ in range(SURFACE_ITERATIONS):
        points, mass, cell_of = _supports(moved, weight)
        k = min(SURFACE_NEIGHBOURS, len(points))
        distance, index = cKDTree(points).query(points, k=k, distance_upper_bound=radius,
                                                workers=max(1, torch.get_num_threads()))  # the same on any count
        distance, index = distance.reshape(len(points), k), index.reshape(len(points), k)
        found = np.isfinite(distance)
        index = np.where(found, index, 0)
        kernel = np.exp(-(np.where(found, distance, 0.0) / (SURFACE_KERNEL * radius)) ** 2)
        centroid, normal = weighted_plane(points[index], np.where(found, mass[index] * kernel, 0.0))
        enough = (found & (mass[index] > 0)).sum(axis=1) >= SURFACE_MIN_SUPPORT
        centroid, normal, enough = centroid[cell_of], normal[cell_of], enough[cell_of]
        height = np.sum((moved - centroid) * normal, axis=1)
        moved -= np.where(enough, height, 0.0)[:, None] * normal
    return moved


def surface_positions_reference(means: np.ndarray, opacity: np.ndarray, radius: float) -> np.ndarray:
    """:func:`surface_positions` point by point: cells by a dictionary, neighbours by sorting all distances."""
    moved = np.asarray(means, dtype=np.float64).reshape(-1, 3).copy()
    weight = np.clip(np.asarray(opacity, dtype=np.float64).reshape(-1), 0.0, 1.0)
    if radius <= 0.0 or len(moved) == 0:
        return moved
    for _ in range(SURFACE_ITERATIONS):
        cells: dict[tuple, list[int]] = {}
        for i, p in enumerate(moved):
            cells.setdefault(tuple(np.floor(p / SURFACE_CELL).astype(np.int64)), []).append(i)
        keys = sorted(cells)
        points = np.array([sum(weight[i] * moved[i] for i in cells[c]) / max(sum(weight[i] for i in cells[c]), 1e-300)
                           for c in keys])
        mass = np.array([sum(weight[i] for i in cells[c]) for c in keys])
        out = moved.copy()
        for s, key in enumerate(keys):
            d = np.linalg.norm(points - points[s], axis=1)
            order = np.argsort(d, kind="stable")[:SURFACE_NEIGHBOURS]
            order = order[d[order] < radius]
            w = mass[order] * np.exp(-(d[order] / (SURFACE_KERNEL * radius)) ** 2)
            if int((mass[order] > 0).sum()) < SURFACE_MIN_SUPPORT:
                continue
            centroid = (w[:, None] * points[order]).sum(0) / max(w.sum(), 1e-300)
            offsets = points[order] - centroid
            _, vectors = np.linalg.eigh((w[:, None, None] * offsets[:, :, None] * offsets[:, None, :]).sum(0))
            normal = vectors[:, 0]
            for i in cells[key]:
                out[i] = moved[i] - np.dot(moved[i] - centroid, normal) * normal
        moved = out
    return moved
