"""What an alignment is given and measured against: its configuration (``AlignConfig``), its target (the scene's
mesh or point cloud, read from a PLY file or a raw tree) and the measures of a splat against that target (the exact
distance to its surface, the transfer's candidates and gate, the build's placement of the aligned Gaussians).
The registration itself is ``registration``.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from seggaussian.labels.config import TransferConfig
from seggaussian.core.knn import nearest_neighbours
from seggaussian.labels.placement import Placement, measure_placement
from seggaussian.sources.layout import find_scene_layout, reader
from seggaussian.labels.transfer import DISTANCE_NOT_MEASURED, densify_labelled_mesh, distance_gate, median_spacing

#: Distances to the transfer's candidates are searched up to this multiple of the gate (farther ones are only
#: "outside the gate", like the transfer's unmeasured ones).
DISTANCE_SEARCH_GATES = 2.0
#: The first bytes of a PLY file (a mesh given as --to must be one).
PLY_MAGIC = b"ply"


@dataclass(frozen=True)
class AlignConfig:
    """``seggaussian align``: registration of a splat onto its scene's mesh."""

    #: Gaussians with an opacity below this take no part in the registration (floaters); all are measured.
    min_opacity: float = 0.1
    #: At most this many Gaussians (seeded subsample of the opaque ones) are registered: a 1M-Gaussian splat
    #: registers in seconds, and 60,000 points fix a room's pose to millimetres.
    max_points: int = 60_000
    #: Area-uniform samples on the mesh the splat is registered to (about 3 cm apart in a 100 m^2 room).
    surface_samples: int = 100_000
    #: Refuse an alignment where less than this share of the opaque Gaussians lies within the transfer's gate of
    #: the surface (besides the build's placement check: ``TransferConfig.min_on_mesh_share``,
    #: ``min_surface_covered_share``, ``max_local_offset``).
    min_fitness: float = 0.5
    #: Seed of the subsamples and of RANSAC.
    seed: int = 0
    #: The transfer whose gate and placement thresholds the aligned splat must pass (the build's defaults).
    transfer: TransferConfig = field(default_factory=TransferConfig)


class AlignTarget(NamedTuple):
    """What a splat is registered to: a mesh (faces) or a point cloud (faces None), in the scene's units."""

    points: np.ndarray  # [P, 3] float64
    faces: np.ndarray | None  # [F, 3] int64
    name: str  # scene id or file stem (seeds the placement's samples, as the build's scene id does)
    path: str  # the file or raw root it came from


class AlignError(ValueError):
    """No alignment found, or a bad input (one line naming the file)."""


# --- inputs -------------------------------------------------------------------------------------------
def load_target(to: str | os.PathLike, scene_id: str | None = None) -> AlignTarget:
    """The mesh of ``to``: a mesh or point-cloud PLY file, or (with ``scene_id``) a scene of a raw tree."""
    to = Path(to)
    if not to.exists():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(to))
    if scene_id is not None:
        if not to.is_dir():
            raise AlignError(f"{to}: --scene needs a raw tree folder, this is a file")
        domain, layout_root = find_scene_layout(to, scene_id)
        scene = reader(domain).read_scene(layout_root, scene_id)
        faces = None if scene.faces is None or not len(scene.faces) else np.asarray(scene.faces, np.int64)
        return AlignTarget(np.asarray(scene.points, np.float64), faces, scene.scene_id, str(to))
    if to.is_dir():
        raise AlignError(f"{to}: a raw tree folder needs --scene ID (or give a mesh PLY file)")
    with open(to, "rb") as f:
        head = f.read(len(PLY_MAGIC))
    if head != PLY_MAGIC:  # checked here: open3d's reader would print its own lines and return nothing
        raise AlignError(f"{to}: not a PLY file (starts with {head!r}); give the scene's mesh as PLY, or a raw tree "
                         "folder with --scene ID")
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(to))
        points = np.asarray(mesh.vertices, np.float64)
        faces = np.asarray(mesh.triangles, np.int64)
        if not len(points):
            points = np.asarray(o3d.io.read_point_cloud(str(to)).points, np.float64)
            faces = np.zeros((0, 3), np.int64)
    if not len(points):
        raise AlignError(f"{to}: no vertices read (not a mesh or point-cloud PLY file?)")
    if not np.isfinite(points).all():
        raise AlignError(f"{to}: {int((~np.isfinite(points).all(axis=1)).sum())} vertices with NaN/Inf coordinates")
    return AlignTarget(points, faces if len(faces) else None, to.name.split(".")[0], str(to))


# --- measures against the target ---------------------------------------------------------------------
def _surface_distance(target: AlignTarget):
    """``distance(x [N, 3]) -> [N]`` to the target's surface: exact point-to-triangle for a mesh (open3d
    raycasting scene), nearest point for a point cloud."""
    if target.faces is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(target.points)
        return lambda x: np.asarray(tree.query(x, k=1, workers=-1)[0], np.float64)
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(target.points, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(target.faces, np.uint32)))
    return lambda x: scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(x, np.float32))).numpy().astype(
        np.float64)


def transfer_candidates(target: AlignTarget, config: TransferConfig) -> tuple[np.ndarray, float]:
    """(the transfer's candidate points: vertices plus samples along the faces, its distance gate)."""
    cand = target.points
    if target.faces is not None and config.mesh_sample_spacing > 0:
        samples, _ = densify_labelled_mesh(target.points, target.faces, config.mesh_sample_spacing)
        cand = np.concatenate([cand, samples])
    gate = distance_gate(median_spacing(nearest_neighbours(cand, config.backend), cand, config), config)
    return cand, gate


def measure_aligned(means: np.ndarray, opacities: np.ndarray, target: AlignTarget, cand: np.ndarray, gate: float,
                    seed: int = 0) -> Placement:
    """The build's placement of Gaussians already in the scene's frame: nearest-candidate distances (the
    transfer's, ``transfer_candidates``) within ``gate``, then ``measure_placement``."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(cand).query(means, k=1, distance_upper_bound=DISTANCE_SEARCH_GATES * gate, workers=-1)
    d = np.where(np.isfinite(d), d, DISTANCE_NOT_MEASURED)  # far beyond the gate: as not measured
    return measure_placement(means, opacities, d, gate, target.points, target.faces, target.name, seed)
