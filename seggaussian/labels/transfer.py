"""Label transfer: every Gaussian takes the labels of its nearest source point, within a distance gate.

Data flow: ``points`` (mesh vertices + surface samples / scan points) -> candidate points -> KD-tree ->
one nearest-neighbour query for the Gaussian centres inside the (enlarged) bounding box of the
candidates -> labels, distances, statistics.

Conventions (documented again in ``data_specs/SHARDS.md``):
- Candidates are all points, labelled or not (``TransferConfig.candidates = "all"``, the default):
  a Gaussian whose nearest point is unlabelled (no group, masked, None-mapped or out of the
  vocabulary) stays ignore, instance and multilabel included, so labels never spill from a labelled
  surface onto an unlabelled one beside it. ``"labelled"`` (only points with a label are candidates:
  every Gaussian within the gate of *some* labelled point gets that label) is kept as an option for
  sources whose unlabelled points are noise rather than unlabelled surfaces.
- The gate is ``max(gate_min, gate_factor x median spacing)``; the spacing is measured between
  *distinct* coordinates (exact duplicates, e.g. the vertices of a mesh split at seams, are skipped),
  so it is the sampling density of the surface and never 0 because of repeated points.
- ``distances`` holds the Euclidean distance (metres, float32) to the nearest candidate for every
  Gaussian that was queried, including those beyond the gate. Gaussians that were not queried
  (outside the box, non-finite centre, no candidate at all) get ``DISTANCE_NOT_MEASURED`` (-1): the
  array never holds inf or NaN.
- Points marked ``hidden`` (label points no train view sees: ``seggaussian.labels.occlusion``) are never
  candidates, so their label cannot reach across the gate; the Gaussians of ``on_surface`` lie on such a surface and
  take the labels of the point named for each instead (its distance is theirs to that surface). They are counted
  as ``on_hidden_surface``.
- Every Gaussian that ends with IGNORE_LABEL is counted under exactly one reason in ``TransferStats``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.labels.config import TransferConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.knn import nearest_neighbours

#: Distance written for a Gaussian that was never queried (outside the box, non-finite centre, or no
#: candidate point): a finite, impossible distance instead of inf so that columns stay NaN/Inf-free.
DISTANCE_NOT_MEASURED = -1.0
#: Quantiles of the measured distances reported per scene.
DISTANCE_QUANTILES = (0.5, 0.9, 0.99, 1.0)
#: Rows per block of the brute-force reference (bounds its [block, P] distance matrix).
REFERENCE_BLOCK = 256
#: Neighbours queried per sampled point when estimating the spacing: the first one at a distance > 0 is
#: its nearest *distinct* point. A point with this many exact copies of itself (never seen in meshes,
#: which repeat a vertex at most a few times at seams) is left out of the median and counted.
SPACING_NEIGHBOURS = 8


class TransferStats(NamedTuple):
    """Per-scene counts of a transfer. Ignored Gaussians are split by reason (they sum to ``ignored``).

    Fields:
        num_gaussians, num_points, num_candidates: input sizes (candidates = points that may give labels).
        spacing: median distance from a candidate to its nearest distinct candidate (metres; exact duplicate
            coordinates skipped; 0 when fewer than 2 distinct candidates).
        gate: distance gate used (metres).
        box_margin: effective bounding-box margin (metres) = max(config margin, gate).
        outside_box: Gaussians outside the enlarged box, ignored without a query.
        nonfinite: Gaussians with a NaN/Inf centre, ignored without a query.
        no_candidates: Gaussians ignored because there was no candidate point at all.
        beyond_gate: queried Gaussians whose nearest candidate is farther than the gate.
        unlabelled_nearest: (candidates="all") Gaussians within the gate whose nearest point is unlabelled, and
            Gaussians on an unlabelled hidden surface.
        on_hidden_surface: Gaussians labelled by the hidden surface they lie on (``on_surface``), ignore included.
        ignored: total Gaussians with IGNORE_LABEL; ``ignored_share`` = ignored / num_gaussians (0 if none).
        distance_quantiles: {"q50", "q90", "q99", "max"} of the measured distances (0.0 when none).
        class_histogram: {class id: count} of the transferred semantic labels (IGNORE excluded).
    """

    num_gaussians: int
    num_points: int
    num_candidates: int
    spacing: float
    gate: float
    box_margin: float
    outside_box: int
    nonfinite: int
    no_candidates: int
    beyond_gate: int
    unlabelled_nearest: int
    on_hidden_surface: int
    ignored: int
    ignored_share: float
    distance_quantiles: dict
    class_histogram: dict

    def to_dict(self) -> dict:
        """JSON-ready (class ids as string keys, as JSON would write them anyway)."""
        out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in self._asdict().items()}
        out["class_histogram"] = {str(k): v for k, v in self.class_histogram.items()}
        return out


class TransferResult(NamedTuple):
    """Labels of N Gaussians.

    Fields:
        semantic: ``[N]`` int32 class id or IGNORE_LABEL.
        instance: ``[N]`` int32 instance id or IGNORE_LABEL.
        multilabel: ``[N, 3]`` int32 up to three class ids (IGNORE_LABEL padded).
        distances: ``[N]`` float32 distance to the nearest candidate, or DISTANCE_NOT_MEASURED.
        stats: ``TransferStats``.
    """

    semantic: np.ndarray
    instance: np.ndarray
    multilabel: np.ndarray
    distances: np.ndarray
    stats: TransferStats


class PreparedInputs(NamedTuple):
    """Validated inputs shared by the fast path and the reference."""

    means: np.ndarray  # [N, 3] float64
    points: np.ndarray  # [P, 3] float64
    semantic: np.ndarray  # [P] int32
    instance: np.ndarray  # [P] int32
    multilabel: np.ndarray  # [P, 3] int32
    candidate_index: np.ndarray  # [C] int64 rows of points that may give labels
    all_candidates: bool  # candidate_index == arange(P)
    on_surface: HiddenSurfaceHits  # Gaussians on a hidden surface and the point whose labels they take


class HiddenSurfaceHits(NamedTuple):
    """Gaussians that lie on a surface no train view sees (``seggaussian.labels.occlusion.on_hidden_surface``).

    Fields:
        rows: ``[R]`` int64 rows of the Gaussians, ascending.
        vertex: ``[R]`` int64 the point whose labels each takes (a mesh vertex: the largest barycentric weight of its
            closest point on its closest triangle).
        distances: ``[R]`` float32 distance (metres) from each Gaussian centre to that closest point.
    """

    rows: np.ndarray
    vertex: np.ndarray
    distances: np.ndarray


# --- public API ---------------------------------------------------------------------------------
def transfer_labels(
    gaussian_means: np.ndarray,  # [N, 3]
    points: np.ndarray,  # [P, 3]
    semantic: np.ndarray,  # [P]
    instance: np.ndarray,  # [P]
    multilabel: np.ndarray | None = None,  # [P, 3]
    config: TransferConfig | None = None,
    hidden: np.ndarray | None = None,  # [P] bool
    on_surface: HiddenSurfaceHits | None = None,
) -> TransferResult:
    """Nearest-candidate labels for every Gaussian centre (KD-tree), gated by distance.

    ``hidden`` points are never candidates; the Gaussians of ``on_surface`` take the labels of their point
    (``on_surface.vertex`` indexes ``points``) whatever the nearest candidate (module docstring).
    Raises ValueError naming the argument for wrong shapes or non-finite points.
    """
    config = config or TransferConfig()
    prep = prepare_inputs(gaussian_means, points, semantic, instance, multilabel, config, hidden, on_surface)
    cand_points = prep.points if prep.all_candidates else prep.points[prep.candidate_index]
    query = nearest_neighbours(cand_points, config.backend)
    spacing = median_spacing(query, cand_points, config)
    gate = distance_gate(spacing, config)
    query_mask, nonfinite = _prefilter(prep.means, cand_points, max(config.box_margin, gate))
    n = len(prep.means)
    if len(cand_points) and n and query_mask.all():  # common case: no row copies
        d, i = query(prep.means, 1)
        nearest = i[:, 0] if prep.all_candidates else prep.candidate_index[i[:, 0]]
        distances = d[:, 0].astype(np.float32)
    else:
        query_rows = np.flatnonzero(query_mask)
        nearest = np.full(n, -1, np.int64)
        distances = np.full(n, DISTANCE_NOT_MEASURED, np.float32)
        if len(query_rows) and len(cand_points):
            d, i = query(prep.means[query_rows], 1)
            nearest[query_rows] = prep.candidate_index[i[:, 0]]
            distances[query_rows] = d[:, 0].astype(np.float32)
    return _finish(prep, nearest, distances, spacing, gate, max(config.box_margin, gate), query_mask, nonfinite)


def transfer_labels_reference(
    gaussian_means: np.ndarray,
    points: np.ndarray,
    semantic: np.ndarray,
    instance: np.ndarray,
    multilabel: np.ndarray | None = None,
    config: TransferConfig | None = None,
    gate: float | None = None,
    hidden: np.ndarray | None = None,
    on_surface: HiddenSurfaceHits | None = None,
) -> TransferResult:
    """Brute-force reference of ``transfer_labels``: a per-row box test, then every remaining finite
    Gaussian is compared with every candidate in dense distance blocks (no tree, no sampling).

    ``gate`` overrides the spacing-derived gate (the fast path's spacing estimate is sampled; tests pass
    the same gate to both through ``TransferConfig.max_distance``).
    """
    config = config or TransferConfig()
    prep = prepare_inputs(gaussian_means, points, semantic, instance, multilabel, config, hidden, on_surface)
    cand_points = prep.points[prep.candidate_index]
    spacing = _median_spacing_reference(cand_points)
    gate = gate if gate is not None else distance_gate(spacing, config)
    margin = max(config.box_margin, gate)
    n = len(prep.means)
    nearest = np.full(n, -1, np.int64)
    distances = np.full(n, DISTANCE_NOT_MEASURED, np.float32)
    finite = np.isfinite(prep.means).all(axis=1)
    outside = np.zeros(n, bool)
    if len(cand_points):
        lo, hi = cand_points.min(axis=0) - margin, cand_points.max(axis=0) + margin
        for r in range(n):
            if finite[r] and not ((prep.means[r] >= lo).all() and (prep.means[r] <= hi).all()):
                outside[r] = True
        for start in range(0, n, REFERENCE_BLOCK):
            rows = np.arange(start, min(n, start + REFERENCE_BLOCK))
            rows = rows[finite[rows] & ~outside[rows]]
            if not len(rows):
                continue
            diff = prep.means[rows, None, :] - cand_points[None, :, :]
            d2 = np.einsum("ijk,ijk->ij", diff, diff)
            j = np.argmin(d2, axis=1)
            nearest[rows] = prep.candidate_index[j]
            distances[rows] = np.sqrt(d2[np.arange(len(rows)), j]).astype(np.float32)
    return _finish(prep, nearest, distances, spacing, gate, margin, finite & ~outside, int((~finite).sum()))


# --- steps --------------------------------------------------------------------------------------
def prepare_inputs(means, points, semantic, instance, multilabel, config: TransferConfig, hidden=None,
                   on_surface: HiddenSurfaceHits | None = None) -> PreparedInputs:
    """Checked float64/int32 copies of the inputs and the candidate points (ValueError naming a bad input)."""
    means = np.asarray(means, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"transfer: gaussian_means has shape {means.shape}, expected (N, 3)")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"transfer: points has shape {points.shape}, expected (P, 3)")
    p = len(points)
    semantic = np.asarray(semantic)
    instance = np.asarray(instance)
    if semantic.shape != (p,):
        raise ValueError(f"transfer: semantic has shape {semantic.shape}, expected ({p},)")
    if instance.shape != (p,):
        raise ValueError(f"transfer: instance has shape {instance.shape}, expected ({p},)")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise ValueError(f"transfer: points holds {bad} rows with NaN/Inf coordinates")
    semantic = semantic.astype(np.int32, copy=False)
    instance = instance.astype(np.int32, copy=False)
    if p and (semantic.min() < 0 or semantic.max() > IGNORE_LABEL):
        raise ValueError(f"transfer: semantic ids must lie in 0..{IGNORE_LABEL} (got {semantic.min()}..{semantic.max()})")
    if multilabel is None:
        multilabel = np.full((p, 3), IGNORE_LABEL, np.int32)
        multilabel[:, 0] = semantic
    else:
        multilabel = np.asarray(multilabel)
        if multilabel.shape != (p, 3):
            raise ValueError(f"transfer: multilabel has shape {multilabel.shape}, expected ({p}, 3)")
        multilabel = multilabel.astype(np.int32, copy=False)
    if config.candidates == "labelled":
        candidate_index = np.flatnonzero(semantic != IGNORE_LABEL)
    elif config.candidates == "all":
        candidate_index = np.arange(p)
    else:
        raise ValueError(f"transfer: candidates must be 'labelled' or 'all', got {config.candidates!r}")
    if hidden is not None:
        hidden = np.asarray(hidden)
        if hidden.shape != (p,) or hidden.dtype != bool:
            raise ValueError(f"transfer: hidden must be a ({p},) bool mask, got {hidden.shape} {hidden.dtype}")
        candidate_index = candidate_index[~hidden[candidate_index]]
    candidate_index = candidate_index.astype(np.int64, copy=False)
    if on_surface is None:
        on_surface = HiddenSurfaceHits(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
    else:
        on_surface = HiddenSurfaceHits(*(np.asarray(a) for a in on_surface))
        r = len(on_surface.rows)
        if any(a.shape != (r,) for a in on_surface):
            raise ValueError("transfer: on_surface rows, vertex and distances must be equally long 1-D arrays")
        if r and (on_surface.rows.min() < 0 or on_surface.rows.max() >= len(means)
                  or len(np.unique(on_surface.rows)) != r):
            raise ValueError(f"transfer: on_surface rows must be distinct Gaussians in 0..{len(means) - 1}")
        if r and (on_surface.vertex.min() < 0 or on_surface.vertex.max() >= p):
            raise ValueError(f"transfer: on_surface vertex must index points 0..{p - 1}")
        if r and not (np.isfinite(on_surface.distances).all() and on_surface.distances.min() >= 0):
            raise ValueError("transfer: on_surface distances must be finite and >= 0")
    return PreparedInputs(means, points, semantic, instance, multilabel, candidate_index, len(candidate_index) == p,
                          on_surface)


def median_spacing(query, cand_points: np.ndarray, config: TransferConfig) -> float:
    """Median distance from a (seeded) sample of candidates to their nearest distinct candidate.

    ``query(x [Q, 3], k) -> (distances [Q, k] ascending, indices)`` searches the candidates (the caller's
    KD-tree). Exact duplicates are skipped: of the ``SPACING_NEIGHBOURS`` nearest candidates of a sampled
    point, the first at a distance > 0 counts (the point itself and its copies are at distance 0).
    """
    if len(cand_points) < 2:
        return 0.0
    rng = np.random.default_rng(config.seed)
    m = min(config.spacing_samples, len(cand_points))
    sample = np.sort(rng.choice(len(cand_points), size=m, replace=False))
    k = min(SPACING_NEIGHBOURS, len(cand_points))
    d, _ = query(cand_points[sample], k)
    d = np.asarray(d, np.float64).reshape(m, k)
    distinct = d > 0.0
    found = distinct.any(axis=1)
    if not found.any():
        return 0.0
    first = d[found, np.argmax(distinct[found], axis=1)]
    return float(np.median(first))


def _median_spacing_reference(cand_points: np.ndarray) -> float:
    """Exact median nearest-distinct-point distance over all distinct candidates (brute force)."""
    unique = np.unique(cand_points + 0.0, axis=0)  # + 0.0: -0.0 and 0.0 are one coordinate
    if len(unique) < 2:
        return 0.0
    out = np.empty(len(unique))
    for start in range(0, len(unique), REFERENCE_BLOCK):
        block = unique[start:start + REFERENCE_BLOCK]
        diff = block[:, None, :] - unique[None, :, :]
        d2 = np.einsum("ijk,ijk->ij", diff, diff)
        d2[np.arange(len(block)), np.arange(start, start + len(block))] = np.inf
        out[start:start + len(block)] = np.sqrt(d2.min(axis=1))
    return float(np.median(out))


def distance_gate(spacing: float, config: TransferConfig) -> float:
    """The transfer's distance gate: ``max_distance`` when given, else ``max(gate_min, gate_factor x spacing)``."""
    if config.max_distance is not None:
        if not config.max_distance > 0:
            raise ValueError(f"transfer: max_distance must be > 0, got {config.max_distance}")
        return float(config.max_distance)
    return float(max(config.gate_min, config.gate_factor * spacing))


def _prefilter(means: np.ndarray, cand_points: np.ndarray, margin: float) -> tuple[np.ndarray, int]:
    """(rows to query: finite and inside the enlarged box, count non-finite)."""
    if not len(cand_points):
        finite = np.isfinite(means).all(axis=1)
        return np.zeros(len(means), bool), int((~finite).sum())
    lo = cand_points.min(axis=0) - margin
    hi = cand_points.max(axis=0) + margin
    if len(means):
        mn, mx = means.min(axis=0), means.max(axis=0)  # NaN propagates, so all-finite bounds mean no NaN
        if np.isfinite(mn).all() and np.isfinite(mx).all() and (mn >= lo).all() and (mx <= hi).all():
            return np.ones(len(means), bool), 0  # fast path: everything inside
    finite = np.isfinite(means).all(axis=1)
    with np.errstate(invalid="ignore"):
        inside = ((means >= lo) & (means <= hi)).all(axis=1)
    return finite & inside, int((~finite).sum())


def _finish(prep: PreparedInputs, nearest, distances, spacing, gate, margin, query_mask, nonfinite) -> TransferResult:
    """Labels and statistics from each Gaussian's nearest candidate (``nearest`` -1 where not queried), after the
    Gaussians on a hidden surface took their surface's point."""
    n = len(prep.means)
    forced = np.zeros(n, bool)
    if len(prep.on_surface.rows):
        nearest = nearest.copy()
        distances = distances.copy()
        nearest[prep.on_surface.rows] = prep.on_surface.vertex
        distances[prep.on_surface.rows] = prep.on_surface.distances
        forced[prep.on_surface.rows] = True
    finite = np.isfinite(prep.means).all(axis=1)
    outside_box = int((finite & ~query_mask & ~forced).sum()) if len(prep.candidate_index) else 0
    queried = nearest >= 0
    within = queried & ((distances <= gate) | forced)
    safe = np.where(within, nearest, 0) if len(prep.points) else np.zeros(n, np.int64)
    if len(prep.points):
        sem = np.where(within, prep.semantic[safe], IGNORE_LABEL).astype(np.int32, copy=False)
        inst = np.where(within, prep.instance[safe], IGNORE_LABEL).astype(np.int32, copy=False)
        multi = np.where(within[:, None], prep.multilabel[safe], IGNORE_LABEL).astype(np.int32, copy=False)
    else:
        sem = np.full(n, IGNORE_LABEL, np.int32)
        inst = np.full(n, IGNORE_LABEL, np.int32)
        multi = np.full((n, 3), IGNORE_LABEL, np.int32)
    unlabelled = within & (sem == IGNORE_LABEL)
    unlabelled_nearest = int(unlabelled.sum())
    if unlabelled_nearest:  # only with candidates="all"
        inst[unlabelled] = IGNORE_LABEL
        multi[unlabelled] = IGNORE_LABEL
    no_candidates = int((finite & ~forced).sum()) if not len(prep.candidate_index) else 0
    beyond_gate = int((queried & ~within).sum())
    ignored = int((sem == IGNORE_LABEL).sum())
    measured = distances[queried]
    if len(measured):
        q = np.quantile(measured.astype(np.float64), DISTANCE_QUANTILES)
        quantiles = {"q50": float(q[0]), "q90": float(q[1]), "q99": float(q[2]), "max": float(q[3])}
    else:
        quantiles = {"q50": 0.0, "q90": 0.0, "q99": 0.0, "max": 0.0}
    counts_all = np.bincount(sem[sem != IGNORE_LABEL]) if ignored < n else np.zeros(0, np.int64)
    ids = np.flatnonzero(counts_all)
    counts = counts_all[ids]
    stats = TransferStats(
        num_gaussians=n,
        num_points=len(prep.points),
        num_candidates=len(prep.candidate_index),
        spacing=float(spacing),
        gate=float(gate),
        box_margin=float(margin),
        outside_box=int(outside_box),
        nonfinite=int(nonfinite),
        no_candidates=no_candidates,
        beyond_gate=beyond_gate,
        unlabelled_nearest=unlabelled_nearest,
        on_hidden_surface=int(forced.sum()),
        ignored=ignored,
        ignored_share=float(ignored / n) if n else 0.0,
        distance_quantiles=quantiles,
        class_histogram={int(i): int(c) for i, c in zip(ids, counts)},
    )
    return TransferResult(sem, inst, multi, distances, stats)


# --- denser labelled points on a mesh ------------------------------------------------------------------
def densify_labelled_mesh(
    vertices: np.ndarray,  # [P, 3]
    faces: np.ndarray,  # [F, 3]
    spacing: float,
    *labels: np.ndarray,  # each [P] or [P, k]
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Labelled points on the triangles of a mesh, about ``spacing`` apart (regular barycentric grid of
    ``ceil(longest edge / spacing)`` steps per triangle; the corners themselves are not repeated).

    Each sample takes the labels of the triangle corner with the largest barycentric weight (ties: the
    first corner), i.e. the label it would get from the nearest vertex of its own triangle. Used when a
    mesh's vertices are farther apart than the gaps between differently labelled surfaces (a window 2 cm in
    front of a wall): the nearest *surface* label then wins instead of a vertex of the surface behind.
    Samples on an edge shared by two triangles are generated by both; the copy from the later triangle
    (exact same coordinates) is dropped, so every sample is one distinct point (the transfer's spacing
    estimate and its nearest-point choice see each surface point once).
    Returns (points [S, 3], [labels of the samples, one array per ``labels`` argument]).
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if not len(faces) or not spacing > 0:
        return np.zeros((0, 3)), [np.asarray(l)[:0] for l in labels]
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    longest = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                               np.linalg.norm(a - c, axis=1)]), axis=0)
    steps = np.ceil(longest / spacing).astype(np.int64)
    points_out, labels_out = [], [[] for _ in labels]
    for n in np.unique(steps[steps >= 2]):
        tri = np.flatnonzero(steps == n)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j <= n) & ~(((i == 0) & (j == 0)) | ((i == n) & (j == 0)) | ((i == 0) & (j == n)))
        bary = np.stack([n - i[keep] - j[keep], i[keep], j[keep]], axis=1).astype(np.float64) / n  # [G, 3]
        corner = np.argmax(bary, axis=1)  # [G]
        corners = faces[tri]  # [T, 3]
        pts = np.einsum("gk,tkd->tgd", bary, vertices[corners]).reshape(-1, 3)
        points_out.append(pts)
        src = corners[:, corner].reshape(-1)  # [T * G] vertex giving the label
        for out, lab in zip(labels_out, labels):
            out.append(np.asarray(lab)[src])
    if not points_out:
        return np.zeros((0, 3)), [np.asarray(l)[:0] for l in labels]
    points = np.concatenate(points_out)
    keep = first_occurrences(points)
    return points[keep], [np.concatenate(o)[keep] for o in labels_out]


def first_occurrences(points: np.ndarray) -> np.ndarray:
    """``[U]`` sorted row indices of the first occurrence of each distinct row of ``points`` ``[S, 3]``
    (exact float equality; -0.0 equals 0.0)."""
    rows = np.ascontiguousarray(np.asarray(points, np.float64) + 0.0)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
    _, first = np.unique(keys, return_index=True)
    return np.sort(first)
