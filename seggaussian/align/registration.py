"""Registration of a splat onto its scene: the similarity ``world_from_splat`` (rotation, translation, uniform
scale) that puts a splat exported in a trainer's own frame (gsplat's normalized world, nerfstudio's auto-oriented
frame) onto the scene's mesh. Opt-in: ``seggaussian align`` writes the transform, the user passes it back with
``--transform``; nothing here moves a splat silently.

Algorithm (``align_gaussians``):

1. **Registration points.** Gaussians with an opacity below ``AlignConfig.min_opacity`` are dropped (floaters are
   mostly transparent); at most ``AlignConfig.max_points`` of the rest are kept (seeded subsample), and of those
   the isolated ones (opaque floaters: ``_drop_isolated``) are left out. The target is
   ``AlignConfig.surface_samples`` area-uniform samples of the mesh (``placement.sample_surface``; a point cloud
   is subsampled).
2. **Normalization.** Each cloud is recentred on its trimmed centroid and divided by its robust radius (the
   ``RADIUS_QUANTILE`` quantile of the distances to that centre): the unknown scale is left as a factor near 1.
3. **Global registration** (``_coarse_candidates``), on clouds voxel-downsampled to ``COARSE_VOXEL``:

   * for each factor of ``SCALE_GRID`` (a partly captured splat's robust radius is not its mesh's), normals,
     FPFH features and open3d's RANSAC on feature matches with a similarity estimate (``with_scaling``, seeded);
   * the 24 poses matching the principal axes of the two clouds (every axis order and sign), centroid on
     centroid;
   * the best pose so far turned by 90, 180 and 270 degrees about each of the mesh's principal axes (a box-shaped
     room is easily registered turned).

   Each pose is polished by a short scaled point-to-point ICP and scored by ``fitness x coverage`` (share of the
   splat's points near the mesh times share of the mesh's points near the splat: a splat shrunk onto one wall
   has the first high and the second low). The ``FINE_CANDIDATES`` best distinct poses go on.
4. **Refinement** (``_refine``). Each candidate: scaled point-to-point ICP (open3d,
   ``TransformationEstimationPointToPoint(with_scaling=True)``) on ``SCORING_POINTS`` registration points against
   the surface samples, in the scene's units, at distances halving from one coarse voxel to
   ``FINAL_ICP_GATE_SHARE x`` the transfer's gate; scored again (exact surface distance within the gate x
   coverage). The best is refined once more on all registration points.
5. **Verdict.** The aligned Gaussians (all of them) are measured as the build measures them
   (``placement.measure_placement`` with the transfer's candidates, gate and distances). ``fitness`` is the
   share of the registration points (opaque subsample) within the gate of the surface (exact point-to-triangle
   distance for a mesh), ``residual_m`` the RMS of those distances. ``alignment_failure`` refuses a result that
   fails the build's placement check (both shares and the local offset, ``placement.placement_failure``) or is
   below ``AlignConfig.min_fitness``.

Limits, measured on the synthetic rooms of seed 0 with random rotations and scales 0.1-3 (2026-11): the pose was
found for every whole room (oracle Gaussians 8 of 8; CPU-fitted splats of ``benchmarks/placement_thresholds.py``,
4 rooms, 8 of 8; oracle Gaussians with 2 cm noise and 50 % more opaque floaters through the room 6 of 6), for half a
room 3 of 6 times (one refused, two wrong poses accepted). No check can tell a right pose from a wrong one that fits
as well: a wrong pose of a partial splat, or the splat of another room of the same box shape registered onto this
room's walls (measured: 67 % of its opacity on the mesh, accepted), passes the build's thresholds too.

The transform maps splat coordinates to the scene's: ``x_scene = s R x_splat + t``, written as a row-major 4x4
``world_from_splat`` (the ``--transform`` JSON format, ``seggaussian.frames``). RANSAC runs on open3d's thread
pool: reruns may pick a different (equally good) coarse pose, which the refinement brings to the same result.
"""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from seggaussian.util.atomic import write_json_atomic
from seggaussian.align.target import (AlignConfig, AlignError, AlignTarget, _surface_distance, load_target,
                                      measure_aligned, transfer_candidates)
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians
from seggaussian.labels.placement import Placement, placement_failure, sample_surface
from seggaussian.util.seeds import scene_seed

#: Quantile of the distances to the centre taken as a cloud's robust radius, and the share of the points nearest
#: the median averaged for the trimmed centre (floaters and far outliers beyond it move neither).
RADIUS_QUANTILE = 0.9
#: Floor of a robust radius: a cloud of one repeated point still normalizes (and its alignment is refused).
RADIUS_FLOOR = 1e-9
#: Neighbour whose distance measures a registration point's isolation, and the multiple of the median of that
#: distance above which a point is isolated (an opaque floater). On the synthetic rooms with 50 % more Gaussians
#: spread through the room, 2x drops about 70 % of the floaters and under 5 % of the surface points.
ISOLATION_NEIGHBOURS = 8
ISOLATION_FACTOR = 2.0
#: Voxel size of the global registration in normalized units (radius 1): about 15 cm in a 3 m room, a few
#: thousand points per cloud. Swept on the synthetic rooms: 0.035 found the pose less often, 0.05 and 0.07 alike.
COARSE_VOXEL = 0.05
#: At most this many downsampled points per cloud in the global registration (seeded subsample): a surface's
#: voxels stay below it, a volume-filling cloud (floaters, an unrelated splat) is thinned.
COARSE_MAX_POINTS = 6_000
#: Normal estimation radius, in voxels, and its neighbour cap.
NORMAL_RADIUS_VOXELS = 2.5
NORMAL_MAX_NN = 30
#: FPFH feature radius, in voxels, and its neighbour cap (open3d's registration tutorial uses 5 voxels / 100).
FPFH_RADIUS_VOXELS = 5.0
FPFH_MAX_NN = 100
#: RANSAC inlier distance, in voxels.
RANSAC_DISTANCE_VOXELS = 1.5
#: RANSAC edge-length check: corresponding edges of a sampled triple differ by at most this ratio, so a try finds
#: the scale only within about 10 % of its factor (hence the grid).
RANSAC_EDGE_SIMILARITY = 0.9
#: Factors multiplying the normalized splat before feature matching: geometric steps of 1.15, each covered by
#: the edge check's tolerance, from 0.76 to 1.32 (the robust radii of a partly captured splat and of its mesh).
SCALE_GRID = (0.76, 0.87, 1.0, 1.15, 1.32)
#: RANSAC iteration cap and confidence per factor (100,000 iterations took 1.5x the time for a success rate within
#: the run-to-run noise on the synthetic rooms).
RANSAC_MAX_ITERATIONS = 20_000
RANSAC_CONFIDENCE = 0.999
#: Correspondences per RANSAC hypothesis (a similarity needs three).
RANSAC_SAMPLE = 3
#: open3d's seed is a 32-bit int: per-factor seeds are reduced modulo this.
RANSAC_SEED_RANGE = 2**31 - 1
#: ICP distances (in coarse voxels, one stage each) polishing each coarse pose, the iteration cap per stage (a
#: pose's basin shows within a few iterations; the refinement converges it), and the distance (in voxels) at which
#: the pose is scored. The 4-voxel stage pulls in principal-axes poses off by up to half a metre (a fitted splat's
#: centroid is not its mesh's): with 2 voxels alone the right pose of a nearly square fitted room was lost.
CANDIDATE_ICP_VOXELS = (4.0, 2.0)
CANDIDATE_ICP_ITERATIONS = 15
CANDIDATE_SCORE_VOXELS = 1.0
#: Distinct coarse poses (best coarse score first) refined and scored.
FINE_CANDIDATES = 3
#: Registration points (seeded subsample) on which every candidate is refined and scored: a room's pose to well
#: within the gate, at a fraction of the full refinement's cost.
SCORING_POINTS = 5_000
#: Iteration cap of every refinement ICP stage.
ICP_MAX_ITERATIONS = 30
#: ICP convergence tolerances (relative fitness and RMSE change between iterations).
ICP_RELATIVE_FITNESS = 1e-6
ICP_RELATIVE_RMSE = 1e-6
#: First refinement distance, in coarse voxels (in the scene's units: the candidates were polished at about that
#: distance); halved per stage.
REFINE_START_VOXELS = 1.0
#: Last refinement distance as a share of the transfer's gate: the Gaussians of an aligned splat lie within the
#: gate, so correspondences beyond half of it are mostly wrong ones.
FINAL_ICP_GATE_SHARE = 0.5
#: A halved refinement distance below this multiple of the final one is replaced by the final one.
STAGE_MERGE = 1.5
#: Each refinement stage's target is voxel-downsampled to this share of the stage's distance.
STAGE_VOXEL_SHARE = 0.25
#: Refinement stages (the narrowest) repeated on all registration points once the best candidate is chosen.
FINAL_STAGES = 2
#: Fewer registration points than this (after the filters) cannot be registered.
MIN_POINTS = 100
#: Reflections are refused: a similarity's determinant must be positive (above this).
MIN_DETERMINANT = 1e-12


class AlignResult(NamedTuple):
    """A registration of a splat onto a target.

    Fields:
        world_from_splat: ``[4, 4]`` float64, ``x_scene = M[:3, :3] x_splat + M[:3, 3]`` (= s R x + t).
        scale, rotation ``[3, 3]``, translation ``[3]``: the similarity's parts.
        residual_m: RMS surface distance (scene units) of the registration points within the gate.
        fitness: share of the opaque Gaussians (the subsample of at most ``max_points``) within the gate of the
            surface.
        placement: the aligned splat's ``Placement`` (what the build checks).
        num_gaussians, num_opaque, num_registered: Gaussians in the splat, above ``min_opacity``, registered (the
            subsample, isolated ones left out).
        coarse: the winning candidate: ``origin`` (which RANSAC factor, principal-axes pose or turn), its coarse
            and fine ``fitness``/``coverage``/``score``, ``candidates`` refined, ``voxel_m``.
        seconds: wall time of the registration.
        failure: one line saying why the alignment is refused, or None.
    """

    world_from_splat: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual_m: float
    fitness: float
    placement: Placement
    num_gaussians: int
    num_opaque: int
    num_registered: int
    coarse: dict
    seconds: float
    failure: str | None

    def to_dict(self) -> dict:
        """JSON-ready; ``world_from_splat`` is what ``--transform`` reads."""
        return {"world_from_splat": np.asarray(self.world_from_splat, float).tolist(),
                "scale": float(self.scale), "rotation": np.asarray(self.rotation, float).tolist(),
                "translation": np.asarray(self.translation, float).tolist(),
                "residual_m": float(self.residual_m), "fitness": float(self.fitness),
                "on_mesh_share": float(self.placement.on_mesh_share),
                "surface_covered_share": float(self.placement.surface_covered_share),
                "gate_m": float(self.placement.gate), "placement": self.placement.to_dict(),
                "num_gaussians": int(self.num_gaussians), "num_opaque": int(self.num_opaque),
                "num_registered": int(self.num_registered), "coarse": dict(self.coarse),
                "seconds": float(self.seconds)}


# --- helpers ------------------------------------------------------------------------------------------
def _normalization(x: np.ndarray) -> tuple[np.ndarray, float]:
    """(trimmed centre [3], robust radius) of a cloud (module docstring, step 2)."""
    centre = np.median(x, axis=0)
    d = np.linalg.norm(x - centre, axis=1)
    centre = x[d <= np.quantile(d, RADIUS_QUANTILE)].mean(axis=0)
    radius = float(np.quantile(np.linalg.norm(x - centre, axis=1), RADIUS_QUANTILE))
    return centre, max(radius, RADIUS_FLOOR)


def _normalizer(centre: np.ndarray, radius: float) -> np.ndarray:
    """4x4 ``x -> (x - centre) / radius``."""
    m = np.eye(4)
    m[:3, :3] /= radius
    m[:3, 3] = -centre / radius
    return m


def _cloud(x: np.ndarray):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(x, np.float64)))


def _features(x: np.ndarray, voxel: float, seed: int):
    """(downsampled cloud, its FPFH features) at ``voxel``; at most ``COARSE_MAX_POINTS`` (seeded subsample, taken
    after the features so that they see the full density)."""
    import open3d as o3d

    down = _cloud(x).voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * voxel,
                                                               max_nn=NORMAL_MAX_NN))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel, max_nn=FPFH_MAX_NN))
    if len(down.points) > COARSE_MAX_POINTS:
        keep = np.sort(np.random.default_rng(seed).choice(len(down.points), COARSE_MAX_POINTS, replace=False))
        down, fpfh = down.select_by_index(keep.tolist()), fpfh.select_by_index(keep.tolist())
    return down, fpfh


def _drop_isolated(x: np.ndarray) -> np.ndarray:
    """Sorted rows of ``x`` that are not isolated: the distance to the ``ISOLATION_NEIGHBOURS``-th nearest other
    point is at most ``ISOLATION_FACTOR`` x its median (an opaque floater floats apart from the surfaces)."""
    if len(x) <= ISOLATION_NEIGHBOURS:
        return np.arange(len(x))
    from scipy.spatial import cKDTree

    d = cKDTree(x).query(x, k=ISOLATION_NEIGHBOURS + 1, workers=-1)[0][:, -1]
    return np.flatnonzero(d <= ISOLATION_FACTOR * np.median(d))


def _icp(source, target, distance: float, init: np.ndarray, iterations: int = ICP_MAX_ITERATIONS) -> np.ndarray:
    """Scaled point-to-point ICP from ``init`` (at most ``iterations``); the refined 4x4."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        source, target, distance, init, reg.TransformationEstimationPointToPoint(with_scaling=True),
        reg.ICPConvergenceCriteria(relative_fitness=ICP_RELATIVE_FITNESS, relative_rmse=ICP_RELATIVE_RMSE,
                                   max_iteration=iterations))
    return np.asarray(result.transformation, np.float64)


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ m[:3, :3].T + m[:3, 3]


def _mutual_score(src: np.ndarray, tgt: np.ndarray, m: np.ndarray, distance: float) -> tuple[float, float]:
    """(share of moved ``src`` within ``distance`` of ``tgt``, share of ``tgt`` within ``distance`` of it)."""
    from scipy.spatial import cKDTree

    moved = _apply(m, src)
    d_src, _ = cKDTree(tgt).query(moved, k=1, distance_upper_bound=distance, workers=-1)
    d_tgt, _ = cKDTree(moved).query(tgt, k=1, distance_upper_bound=distance, workers=-1)
    return float(np.isfinite(d_src).mean()), float(np.isfinite(d_tgt).mean())


def similarity_parts(m: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation [3, 3], translation [3]) of a 4x4 similarity ``s R x + t`` (rotation re-orthonormalized);
    ValueError for a reflection or a degenerate matrix."""
    a = np.asarray(m, np.float64)[:3, :3]
    det = float(np.linalg.det(a))
    if not det > MIN_DETERMINANT:
        raise ValueError(f"not a proper similarity (determinant {det:.3g})")
    scale = det ** (1.0 / 3.0)
    u, _, vt = np.linalg.svd(a / scale)
    return scale, u @ vt, np.asarray(m, np.float64)[:3, 3].copy()


# --- registration -------------------------------------------------------------------------------------
def _cube_rotations() -> list[np.ndarray]:
    """The 24 proper rotations mapping the coordinate axes onto themselves (signed permutations, det +1),
    the identity first."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = np.where(np.array(signs) == 1, -1.0, 1.0)
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def _axis_turns() -> list[np.ndarray]:
    """The 9 rotations by 90, 180 and 270 degrees about one coordinate axis."""
    return [r for r in _cube_rotations() if int(np.isclose(np.diag(r), 1.0).sum()) == 1]


def _principal_frame(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centroid [3], principal axes [3, 3] as columns, a proper rotation)."""
    centre = x.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((x - centre).T))
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return centre, axes


def _pose(source_centre: np.ndarray, target_centre: np.ndarray, r: np.ndarray) -> np.ndarray:
    """4x4 ``x -> r (x - source_centre) + target_centre``."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, target_centre - r @ source_centre
    return m


def _distinct(found: list[tuple[np.ndarray, dict]], points: np.ndarray, count: int) -> list[tuple[np.ndarray, dict]]:
    """The first ``count`` poses of ``found`` (best first) that each move ``points`` more than a coarse voxel (RMS)
    away from where every pose kept before puts them."""
    kept: list[tuple[np.ndarray, dict]] = []
    for m, record in found:
        moved = _apply(m, points)
        if all(np.sqrt(np.mean(np.sum((moved - _apply(k, points)) ** 2, axis=1))) > COARSE_VOXEL for k, _ in kept):
            kept.append((m, record))
            if len(kept) == count:
                break
    return kept


def _coarse_candidates(src: np.ndarray, tgt: np.ndarray, seed: int) -> tuple[list[tuple[np.ndarray, dict]], float]:
    """Global registration (module docstring, step 3): ([(4x4 ``src -> tgt``, record)] of the ``FINE_CANDIDATES``
    best distinct poses, best first; the coarse voxel in the target's units)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    n_s, n_t = _normalizer(*_normalization(src)), _normalizer(*_normalization(tgt))
    radius_t = 1.0 / n_t[0, 0]
    tgt_down, tgt_fpfh = _features(_apply(n_t, tgt), COARSE_VOXEL, seed)
    tgt_pts = np.asarray(tgt_down.points)
    src_pts = np.asarray(_cloud(_apply(n_s, src)).voxel_down_sample(COARSE_VOXEL).points)
    if len(src_pts) > COARSE_MAX_POINTS:
        src_pts = src_pts[np.sort(np.random.default_rng(seed).choice(len(src_pts), COARSE_MAX_POINTS, False))]
    src_cloud = _cloud(src_pts)
    found: list[tuple[np.ndarray, dict]] = []

    def polish(m: np.ndarray, origin: str) -> None:
        """Coarse ICP of a pose (normalized splat -> normalized mesh), scored, added to ``found``."""
        for voxels in CANDIDATE_ICP_VOXELS:
            m = _icp(src_cloud, tgt_down, voxels * COARSE_VOXEL, m, CANDIDATE_ICP_ITERATIONS)
        if np.linalg.det(m[:3, :3]) > MIN_DETERMINANT:
            fitness, coverage = _mutual_score(src_pts, tgt_pts, m, CANDIDATE_SCORE_VOXELS * COARSE_VOXEL)
            found.append((m, {"origin": origin, "coarse_fitness": fitness, "coarse_coverage": coverage,
                              "coarse_score": fitness * coverage}))

    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(RANSAC_EDGE_SIMILARITY),
                reg.CorrespondenceCheckerBasedOnDistance(RANSAC_DISTANCE_VOXELS * COARSE_VOXEL)]
    for factor in SCALE_GRID:
        pre = np.diag([factor, factor, factor, 1.0])
        src_down, src_fpfh = _features(_apply(pre, src_pts), COARSE_VOXEL, seed)
        if min(len(src_down.points), len(tgt_pts)) < RANSAC_SAMPLE:
            continue
        o3d.utility.random.seed(scene_seed(seed, f"align-ransac-{factor}") % RANSAC_SEED_RANGE)
        ransac = reg.registration_ransac_based_on_feature_matching(
            src_down, tgt_down, src_fpfh, tgt_fpfh, False, RANSAC_DISTANCE_VOXELS * COARSE_VOXEL,
            reg.TransformationEstimationPointToPoint(with_scaling=True), RANSAC_SAMPLE, checkers,
            reg.RANSACConvergenceCriteria(RANSAC_MAX_ITERATIONS, RANSAC_CONFIDENCE))
        polish(np.asarray(ransac.transformation, np.float64) @ pre, f"ransac x{factor}")
    (c_s, axes_s), (c_t, axes_t) = _principal_frame(src_pts), _principal_frame(tgt_pts)
    for k, g in enumerate(_cube_rotations()):
        polish(_pose(c_s, c_t, axes_t @ g @ axes_s.T), f"principal axes {k}")
    if not found:
        return [], COARSE_VOXEL * radius_t
    best_m, best_record = max(found, key=lambda c: c[1]["coarse_score"])
    for k, turn in enumerate(_axis_turns()):
        polish(_pose(c_t, c_t, axes_t @ turn @ axes_t.T) @ best_m, f"{best_record['origin']}, turned {k + 1}")
    found.sort(key=lambda c: -c[1]["coarse_score"])
    back = np.linalg.inv(n_t)
    kept = _distinct(found, src_pts, FINE_CANDIDATES)
    return [(back @ m @ n_s, record) for m, record in kept], COARSE_VOXEL * radius_t


def _schedule(tgt: np.ndarray, start: float, final: float) -> list[tuple[float, object]]:
    """[(distance, target cloud)] of a refinement: distances halving from ``start`` while above
    ``STAGE_MERGE x final``, then ``final``; each stage's target is voxel-downsampled to ``STAGE_VOXEL_SHARE`` of
    its distance (open3d's correspondence search visits every target point within the distance: a dense target
    makes the wide stages slow, not more precise)."""
    distances, d = [], start
    while d > STAGE_MERGE * final:
        distances.append(d)
        d /= 2.0
    return [(d, _cloud(tgt).voxel_down_sample(STAGE_VOXEL_SHARE * d)) for d in distances + [final]]


def _refine(source, schedule: list[tuple[float, object]], m: np.ndarray) -> np.ndarray:
    """Scaled point-to-point ICP from ``m`` through the stages of ``_schedule`` (step 4)."""
    for distance, target in schedule:
        m = _icp(source, target, distance, m)
    return m


def align_gaussians(gaussians: Gaussians, target: AlignTarget, config: AlignConfig = AlignConfig(),
                    source: str = "splat") -> AlignResult:
    """Register ``gaussians`` onto ``target`` (module docstring); ``failure`` says when the result is refused.
    ``source`` names the splat in errors (``AlignError`` for too few points or no candidate at all)."""
    import open3d as o3d

    start = time.perf_counter()
    means = np.asarray(gaussians.means, np.float64)
    opacities = gaussians.opacities().astype(np.float64)
    opaque = np.flatnonzero((opacities >= config.min_opacity) & np.isfinite(means).all(axis=1))
    rng = np.random.default_rng(scene_seed(config.seed, f"align-{target.name}"))
    used = opaque if len(opaque) <= config.max_points else np.sort(rng.choice(opaque, config.max_points, False))
    src = means[used[_drop_isolated(means[used])]]
    if len(src) < MIN_POINTS:
        raise AlignError(f"{source}: only {len(src)} of {len(means)} Gaussians are opaque (>= {config.min_opacity}) "
                         f"and not isolated: need {MIN_POINTS} to register")
    tgt = sample_surface(target.points, target.faces, config.surface_samples,
                         scene_seed(config.seed, f"align-surface-{target.name}"))
    if len(tgt) < MIN_POINTS:
        raise AlignError(f"{target.path}: only {len(tgt)} surface points: need {MIN_POINTS} to register")
    cand, gate = transfer_candidates(target, config.transfer)
    distance_to_surface = _surface_distance(target)

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # no warnings on stdout (--json)
        candidates, voxel = _coarse_candidates(src, tgt, config.seed)
        schedule = _schedule(tgt, REFINE_START_VOXELS * voxel, FINAL_ICP_GATE_SHARE * gate)
        scoring = src[np.sort(rng.choice(len(src), min(len(src), SCORING_POINTS), replace=False))]
        scoring_tgt = tgt[rng.choice(len(tgt), min(len(tgt), SCORING_POINTS), replace=False)]
        scoring_cloud = _cloud(scoring)
        best, best_record = None, {"score": -1.0}
        for m, record in candidates:
            m = _refine(scoring_cloud, schedule, m)
            if not np.linalg.det(m[:3, :3]) > MIN_DETERMINANT:
                continue
            fitness = float((distance_to_surface(_apply(m, scoring)) <= gate).mean())
            _, coverage = _mutual_score(scoring, scoring_tgt, m, gate)
            if fitness * coverage > best_record["score"]:
                best, best_record = m, dict(record, fitness=fitness, coverage=coverage, score=fitness * coverage)
        if best is None:
            raise AlignError(f"{source}: no registration candidate onto {target.path} (every one degenerated to a "
                             "zero scale or a reflection)")
        m = _refine(_cloud(src), schedule[-FINAL_STAGES:], best)
    best_record.update(candidates=len(candidates), voxel_m=float(voxel))
    scale, rotation, translation = similarity_parts(m)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = scale * rotation, translation

    aligned = _apply(m, means)
    placement = measure_aligned(aligned, opacities, target, cand, gate, config.transfer.seed)
    d = distance_to_surface(aligned[used])
    inside = d <= gate
    fitness = float(inside.mean())
    residual = float(np.sqrt(np.mean(d[inside] ** 2))) if inside.any() else float("nan")
    result = AlignResult(m, scale, rotation, translation, residual, fitness, placement, len(means), len(opaque),
                         len(src), best_record, time.perf_counter() - start, None)
    return result._replace(failure=alignment_failure(result, config))


def alignment_failure(result: AlignResult, config: AlignConfig) -> str | None:
    """The one-line reason an alignment is refused, or None: the aligned splat must pass the build's placement
    check (``placement.placement_failure`` with the transfer's thresholds) and reach ``min_fitness``."""
    p, t = result.placement, config.transfer
    if (placement_failure(p, t.min_on_mesh_share, t.min_surface_covered_share, t.max_local_offset) is None
            and result.fitness >= config.min_fitness):
        return None
    offset = (f", {100 * p.local_offset:.1f} cm left to a local registration (allowed {100 * t.max_local_offset:.1f})"
              if t.max_local_offset >= 0 else "")
    return (f"the registration did not converge: the best pose puts {100 * p.on_mesh_share:.1f} % of the opacity "
            f"within {100 * p.gate:.1f} cm of the mesh (need {100 * t.min_on_mesh_share:.0f} %), covers "
            f"{100 * p.surface_covered_share:.1f} % of its surface (need {100 * t.min_surface_covered_share:.0f} %)"
            f"{offset}, fitness {result.fitness:.2f} (need {config.min_fitness:.2f}) at scale {result.scale:.3g}: "
            "is this the splat of this scene?")


# --- the command's one call ---------------------------------------------------------------------------
def run_align(splat: str | os.PathLike, to: str | os.PathLike, out: str | os.PathLike, scene_id: str | None = None,
              config: AlignConfig = AlignConfig()) -> tuple[AlignResult, dict]:
    """Read the splat and the target, register, refuse (``AlignError`` naming the splat, nothing written) a result
    that does not converge, else write ``out`` (JSON, atomically). Returns (result, the JSON written)."""
    splat, to, out = Path(splat), Path(to), Path(out)
    if not splat.exists():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(splat))
    target = load_target(to, scene_id)
    gaussians, _, fmt = read_gaussians(splat)
    result = align_gaussians(gaussians, target, config, source=str(splat))
    if result.failure is not None:
        raise AlignError(f"{splat}: no alignment onto {to}{f' scene {scene_id}' if scene_id else ''}: "
                         f"{result.failure}")
    payload = {**result.to_dict(), "splat": str(splat), "format": fmt, "to": str(to), "scene": scene_id,
               "seed": config.seed,
               "usage": f"pass it back with --transform {out} (or save it as <scene>.transform.json)"}
    write_json_atomic(out, payload)
    return result, payload
