"""Initial Gaussians of a fit: scene extent, voxel-averaged points, scales from nearest neighbours.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.core.constants import SH_C0
from seggaussian.fit.config import FitConfig
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.knn import nearest_neighbours

#: Smallest initial nearest-neighbour distance (metres): duplicate points would otherwise give
#: log(0) = -inf scales.
INIT_MIN_NN_DISTANCE = 1e-7
#: Scene extents below this (metres) are degenerate (one camera, or all cameras at one spot);
#: the extent then falls back to the initial points' bounding box.
MIN_SCENE_EXTENT = 1e-6
#: 3DGS scales the camera-centre radius by this factor to get the scene extent.
EXTENT_MARGIN = 1.1


def compute_scene_extent(cameras: Sequence[Camera], points: np.ndarray) -> float:
    """3DGS scene extent: 1.1 x the largest distance of a camera centre from their mean; the half
    diagonal of the points' bounding box when the cameras do not spread."""
    centres = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()) * EXTENT_MARGIN
    if radius < MIN_SCENE_EXTENT:
        radius = 0.5 * float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return max(radius, MIN_SCENE_EXTENT)


def voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points (float64) and colours (float64, 0..255) per occupied voxel, voxels in sorted key order."""
    points = np.asarray(points, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.float64)
    if voxel_size <= 0.0:
        return points, colors
    keys = np.floor((points - points.min(axis=0)) / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((counts.shape[0], 3))
    np.add.at(sums, inverse, points)
    csums = np.zeros((counts.shape[0], 3))
    np.add.at(csums, inverse, colors)
    return sums / counts[:, None], csums / counts[:, None]


def initialize_gaussians(points: np.ndarray, colors: np.ndarray, config: FitConfig,
                         rng: np.random.Generator) -> tuple[Gaussians, dict]:
    """Initial Gaussians at the voxel-averaged points: isotropic scales = mean distance to the
    ``init_knn`` nearest other points (log), identity rotations, opacity ``init_opacity`` (logit),
    SH DC from the point colours, higher SH zero. Returns the Gaussians and counts for the metrics."""
    pts, cols = voxel_downsample(points, colors, config.init_voxel_size)
    stats = {"input_points": int(points.shape[0]), "voxel_points": int(pts.shape[0]), "subsampled_away": 0}
    if pts.shape[0] > config.max_gaussians:
        keep = np.sort(rng.choice(pts.shape[0], size=config.max_gaussians, replace=False))
        stats["subsampled_away"] = int(pts.shape[0] - keep.shape[0])
        pts, cols = pts[keep], cols[keep]
    n = pts.shape[0]
    if n > 1:
        k = min(config.init_knn, n - 1)
        dist, _ = nearest_neighbours(pts, "scipy")(pts, k + 1)
        nn = dist[:, 1:].mean(axis=1)
    else:
        nn = np.full(n, 0.01)
    nn = np.maximum(nn, INIT_MIN_NN_DISTANCE)
    log_scales = np.repeat(np.log(nn)[:, None], 3, axis=1)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    opacity = np.full(n, math.log(config.init_opacity / (1.0 - config.init_opacity)))
    k_coeffs = (config.sh_degree + 1) ** 2
    sh = np.zeros((n, k_coeffs, 3))
    sh[:, 0] = (cols / 255.0 - 0.5) / SH_C0
    return Gaussians.from_arrays(pts, quats, log_scales, opacity, sh), stats
