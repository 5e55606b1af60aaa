"""How well a scene's Gaussians sit on its labelled mesh, and the refusal of a splat that does not.

A splat exported by a trainer in its own frame (gsplat's normalized world, nerfstudio's dataparser frame, an
SPZ read without its RUB -> RDF change) still gets labels from a nearest-neighbour transfer: mostly ignore,
and the rest wrong. Three measurements tell such a splat from an aligned one, whatever its opacity, density or
floaters:

* ``on_mesh_share``: the opacity-weighted share of the Gaussians whose centre lies within the distance gate of
  the mesh (the transfer's own distances: vertices plus dense surface samples; the gate derived from their
  spacing, whatever gate the user set for the labels). Floaters are mostly transparent, so they weigh little; a
  misplaced splat has few Gaussians of any opacity near the mesh.
* ``surface_covered_share``: the share of area-uniform samples on the mesh's triangles (the points, for a point
  cloud) that have a Gaussian centre within the gate. A splat scaled down onto the room's middle may touch a
  few surfaces; it does not cover them. It grows with the number of Gaussians, so its floor is low.
* ``local_offset``: how far a local registration (ICP with scale, from the identity) onto the mesh moves the
  Gaussians. A splat shifted or turned by a fraction of the room keeps much of itself on the floor, ceiling and
  the walls along the shift, which the shares cannot see; its objects and the walls across the shift pull it back.

An aligned scene passes all three thresholds (``TransferConfig.min_on_mesh_share``,
``min_surface_covered_share``, ``max_local_offset``), chosen by measurement (``benchmarks/placement_thresholds.py``,
margins in ``benchmarks/results/stages.md``). A scene that fails one is refused by :func:`check_placement` with
one line naming the figures, the splat's extent and centre against the mesh's, and the likely cause. What no
geometric check can see: a turn that maps the room onto itself (90 degrees in a nearly square room, whose
objects are few); the stage table records where that happened.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.util.seeds import scene_seed

#: Area-uniform surface samples drawn (seeded) to measure the covered share; 20,000 samples give the share to
#: about +-0.35 percentage points (binomial standard error at 50 %), far finer than any threshold margin.
SURFACE_SAMPLES = 20_000
#: Quantiles bounding a robust extent of the splat and the mesh for the refusal's hint (floaters and far
#: outliers outside them do not stretch the box).
EXTENT_QUANTILES = (0.02, 0.98)
#: Gaussians (seeded subsample) and surface samples used by the local registration of ``local_offset``.
ICP_GAUSSIANS = 10_000
ICP_SURFACE_SAMPLES = 40_000
#: Correspondence distances of the local registration, as multiples of the gate, one stage each (coarse to fine),
#: and the iterations per stage. A splat off by less than the first distance is pulled back by its objects and
#: the walls across the shift; farther correspondences (floaters, other surfaces) are left out.
ICP_DISTANCE_FACTORS = (6.0, 3.0, 1.5)
ICP_ITERATIONS = 10
#: A stage stops early once an iteration moves the centres by less than this (metres, RMS): converged.
ICP_CONVERGED = 1e-4
#: Weight floor of the similarity fit (a stage whose correspondences carry no weight stops).
ICP_MIN_WEIGHT = 1e-9
#: Denominator floor of the opacity-weighted share (a scene whose every Gaussian is fully transparent has no
#: weight: its share is 0, not NaN).
WEIGHT_EPS = 1e-12


def fit_similarity(source: np.ndarray, target: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least-squares similarity (R [3,3], t [3], s) with target ~ s R source + t (Umeyama 1991)."""
    w = weights / weights.sum()
    mu_s, mu_t = w @ source, w @ target
    xs, xt = source - mu_s, target - mu_t
    cov = (xt * w[:, None]).T @ xs
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = u @ np.diag(sign) @ vt
    var_s = float(w @ (xs * xs).sum(axis=1))
    scale = float((d * sign).sum() / var_s) if var_s > ICP_MIN_WEIGHT else 1.0
    return rotation, mu_t - scale * rotation @ mu_s, scale


def local_offset(means: np.ndarray, weights: np.ndarray, surface: np.ndarray, gate: float
                 ) -> tuple[float, float, float, float]:
    """How far the splat sits from where the mesh would pull it: a local registration (point-to-point ICP with
    scale, from the identity) of the Gaussian centres onto the surface samples. Returns (RMS displacement of the
    centres under the correction in metres (weighted by opacity), the move of their centroid (m), rotation (degrees) and
    |scale - 1|). An aligned splat barely moves; a splat shifted or turned by a fraction of the room, which the
    shares cannot see along the room's big planes, is pulled back by its objects and the walls across the shift."""
    from scipy.spatial import cKDTree

    if len(means) < 3 or len(surface) < 3:
        return 0.0, 0.0, 0.0, 0.0
    tree = cKDTree(surface)
    moved = means.copy()
    total_r, total_t, total_s = np.eye(3), np.zeros(3), 1.0
    for factor in ICP_DISTANCE_FACTORS:
        for _ in range(ICP_ITERATIONS):
            d, idx = tree.query(moved, k=1, distance_upper_bound=factor * gate, workers=-1)
            keep = np.isfinite(d)
            if keep.sum() < 3 or weights[keep].sum() <= ICP_MIN_WEIGHT:
                break
            r, t, sc = fit_similarity(moved[keep], surface[idx[keep]], weights[keep])
            step = sc * moved @ r.T + t
            change = float(np.sqrt(np.mean(((step - moved) ** 2).sum(axis=1))))
            moved = step
            total_r, total_t, total_s = r @ total_r, sc * r @ total_t + t, sc * total_s
            if change < ICP_CONVERGED:
                break
    w = weights / weights.sum()
    rms = float(np.sqrt(w @ ((moved - means) ** 2).sum(axis=1)))
    centroid = w @ means
    shift = float(np.linalg.norm(total_s * total_r @ centroid + total_t - centroid))
    angle = float(np.degrees(np.arccos(np.clip((np.trace(total_r) - 1.0) / 2.0, -1.0, 1.0))))
    return rms, shift, angle, abs(total_s - 1.0)


class Placement(NamedTuple):
    """How one scene's Gaussians sit on its mesh (all JSON-ready floats/ints).

    Fields:
        on_mesh_share: opacity-weighted share of Gaussians whose centre is within ``gate`` of the mesh.
        on_mesh_share_unweighted: the same share, every Gaussian counted once.
        surface_covered_share: share of the surface samples with a Gaussian centre within ``gate``.
        gate: the distance gate (metres), the transfer's.
        surface_samples: samples drawn on the surface.
        extent_ratio: robust extent of the splat / the mesh's (geometric mean over the three axes).
        centre_offset: distance (metres) between the robust box centres of the splat and the mesh.
        local_offset: RMS displacement (metres) of the Gaussian centres under the local registration onto the
            mesh (``local_offset``); local_shift, local_rotation_deg, local_scale_change: its parts.
    """

    on_mesh_share: float
    on_mesh_share_unweighted: float
    surface_covered_share: float
    gate: float
    surface_samples: int
    extent_ratio: float
    centre_offset: float
    local_offset: float
    local_shift: float
    local_rotation_deg: float
    local_scale_change: float

    def to_dict(self) -> dict:
        return dict(self._asdict())


class PlacementError(ValueError):
    """A scene's Gaussians do not sit on its mesh (one line: both shares, the thresholds, the likely cause)."""


def sample_surface(points: np.ndarray, faces: np.ndarray | None, count: int, seed: int) -> np.ndarray:
    """``count`` points on the mesh, uniform by area (seeded); a point cloud (no faces) is subsampled."""
    points = np.asarray(points, np.float64)
    rng = np.random.default_rng(seed)
    if faces is None or not len(faces):
        if len(points) <= count:
            return points
        return points[np.sort(rng.choice(len(points), size=count, replace=False))]
    faces = np.asarray(faces, np.int64)
    a, b, c = (points[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = float(area.sum())
    if not total > 0:
        return points[:0]
    tri = rng.choice(len(faces), size=count, p=area / total)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0  # fold the unit square onto the triangle: uniform barycentrics
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])


def _robust_box(x: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(low [3], high [3]) corners at ``EXTENT_QUANTILES`` per axis (weighted by repetition-free quantiles)."""
    if weights is None:
        lo, hi = np.quantile(x, EXTENT_QUANTILES, axis=0)
        return lo, hi
    order = np.argsort(x, axis=0)
    cum = np.cumsum(weights[order], axis=0)
    cum /= max(cum[-1, 0], WEIGHT_EPS)
    corners = []
    for q in EXTENT_QUANTILES:
        idx = np.minimum((cum < q).sum(axis=0), len(x) - 1)
        corners.append(x[order[idx, np.arange(3)], np.arange(3)])
    return corners[0], corners[1]


def measure_placement(
    means: np.ndarray,  # [N, 3]
    opacities: np.ndarray,  # [N] in [0, 1]
    distances: np.ndarray,  # [N] distance to the nearest mesh point (transfer), < 0 where not measured
    gate: float,
    points: np.ndarray,  # [P, 3] mesh vertices (or point cloud)
    faces: np.ndarray | None,  # [F, 3] or None
    scene_id: str = "",
    seed: int = 0,
) -> Placement:
    """Both shares of the module docstring, and the extent/centre hint, for one scene."""
    means = np.asarray(means, np.float64)
    opacities = np.asarray(opacities, np.float64)
    distances = np.asarray(distances, np.float64)
    n = len(means)
    finite = np.isfinite(means).all(axis=1)
    within = (distances >= 0) & (distances <= gate) & finite
    weight_total = float(opacities[finite].sum())
    on_mesh = float(opacities[within].sum() / weight_total) if weight_total > WEIGHT_EPS else 0.0
    unweighted = float(within.sum() / n) if n else 0.0
    surface = sample_surface(points, faces, SURFACE_SAMPLES, scene_seed(seed, scene_id))
    covered = 0.0
    if len(surface) and finite.any():
        from scipy.spatial import cKDTree

        tree = cKDTree(means[finite])
        d, _ = tree.query(surface, k=1, distance_upper_bound=gate, workers=-1)
        covered = float(np.isfinite(d).mean())
    extent_ratio, offset = float("nan"), float("nan")
    if finite.any() and len(points):
        s_lo, s_hi = _robust_box(means[finite], opacities[finite])
        m_lo, m_hi = _robust_box(np.asarray(points, np.float64))
        s_ext, m_ext = np.maximum(s_hi - s_lo, 0.0), np.maximum(m_hi - m_lo, 0.0)
        if (m_ext > 0).all() and (s_ext > 0).all():
            extent_ratio = float(np.exp(np.mean(np.log(s_ext / m_ext))))
        offset = float(np.linalg.norm((s_lo + s_hi) / 2 - (m_lo + m_hi) / 2))
    rng = np.random.default_rng(scene_seed(seed + 1, scene_id))
    rows = np.flatnonzero(finite)
    if len(rows) > ICP_GAUSSIANS:
        rows = np.sort(rng.choice(rows, size=ICP_GAUSSIANS, replace=False))
    icp_surface = sample_surface(points, faces, ICP_SURFACE_SAMPLES, scene_seed(seed + 2, scene_id))
    local = (0.0, 0.0, 0.0, 0.0)
    if len(rows) and opacities[rows].sum() > WEIGHT_EPS:
        local = local_offset(means[rows], opacities[rows], icp_surface, gate)
    return Placement(on_mesh, unweighted, covered, float(gate), int(len(surface)),
                     extent_ratio if np.isfinite(extent_ratio) else 0.0, offset if np.isfinite(offset) else 0.0,
                     *(float(v) for v in local))


def placement_failure(placement: Placement, min_on_mesh: float, min_covered: float, max_offset: float
                      ) -> str | None:
    """The one-line reason a scene is refused, or None when both shares reach their thresholds and the local
    registration moves the splat by at most ``max_offset`` metres."""
    offset_ok = max_offset < 0 or placement.local_offset <= max_offset  # negative: check disabled
    if placement.on_mesh_share >= min_on_mesh and placement.surface_covered_share >= min_covered and offset_ok:
        return None
    if placement.on_mesh_share >= min_on_mesh and placement.surface_covered_share >= min_covered:
        return (f"the Gaussians sit {100 * placement.local_offset:.1f} cm (RMS) from where the mesh pulls them "
                f"(allowed {100 * max_offset:.1f} cm): shifted {100 * placement.local_shift:.1f} cm, turned "
                f"{placement.local_rotation_deg:.1f} deg, scaled by {100 * placement.local_scale_change:.1f} % "
                f"({100 * placement.on_mesh_share:.1f} % of their opacity within {placement.gate * 100:.1f} cm of the "
                f"mesh, {100 * placement.surface_covered_share:.1f} % of its surface covered): in another frame? "
                f"see --transform (or seggaussian align)")
    return (f"the Gaussians do not sit on the mesh: {100 * placement.on_mesh_share:.1f} % of their opacity within "
            f"{placement.gate * 100:.1f} cm of it (need {100 * min_on_mesh:.0f} %), "
            f"{100 * placement.surface_covered_share:.1f} % of its surface covered (need {100 * min_covered:.0f} %); "
            f"splat extent {placement.extent_ratio:.2f}x the mesh's, centre {placement.centre_offset:.2f} m away: "
            f"in another frame? see --transform (or seggaussian align)")


def check_placement(placement: Placement, min_on_mesh: float, min_covered: float, max_offset: float,
                    scene_id: str) -> None:
    """Raise :class:`PlacementError` (one line naming the scene) when ``placement_failure`` gives a reason."""
    reason = placement_failure(placement, min_on_mesh, min_covered, max_offset)
    if reason is not None:
        raise PlacementError(f"scene {scene_id}: {reason}")
