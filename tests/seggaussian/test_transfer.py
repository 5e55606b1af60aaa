"""Label transfer: KD-tree fast path against the brute-force reference, gate/prefilter accounting, empties."""

from __future__ import annotations

import numpy as np
import pytest

from seggaussian.labels.config import TransferConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.labels.transfer import (
    DISTANCE_NOT_MEASURED,
    densify_labelled_mesh,
    first_occurrences,
    transfer_labels,
    transfer_labels_reference,
)
from seggaussian.labels.scoring import label_accuracy, surface_labels


def _random_inputs(rng, n=400, p=300, ignore_share=0.2, spread=1.0):
    points = rng.uniform(0, 1, (p, 3))
    semantic = rng.integers(0, 100, p).astype(np.int32)
    semantic[rng.random(p) < ignore_share] = IGNORE_LABEL
    instance = rng.integers(0, 50, p).astype(np.int32)
    multilabel = rng.integers(0, 100, (p, 3)).astype(np.int32)
    means = rng.uniform(-spread, 1 + spread, (n, 3))
    return means, points, semantic, instance, multilabel


def _assert_same(a, b):
    np.testing.assert_array_equal(a.semantic, b.semantic)
    np.testing.assert_array_equal(a.instance, b.instance)
    np.testing.assert_array_equal(a.multilabel, b.multilabel)
    np.testing.assert_allclose(a.distances, b.distances, rtol=1e-6, atol=1e-7)
    for key in ("outside_box", "nonfinite", "no_candidates", "beyond_gate", "unlabelled_nearest", "on_hidden_surface",
                "ignored"):
        assert getattr(a.stats, key) == getattr(b.stats, key), key
    assert a.stats.class_histogram == b.stats.class_histogram


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("candidates", ["labelled", "all"])
@pytest.mark.parametrize("gate", [0.03, 0.1, 0.4])
def test_matches_brute_force(seed, candidates, gate):
    rng = np.random.default_rng(seed)
    means, points, sem, inst, multi = _random_inputs(rng)
    config = TransferConfig(candidates=candidates, max_distance=gate)
    fast = transfer_labels(means, points, sem, inst, multi, config)
    ref = transfer_labels_reference(means, points, sem, inst, multi, config)
    _assert_same(fast, ref)
    assert fast.stats.ignored == (fast.semantic == IGNORE_LABEL).sum()


def _ignored_by_reason(stats) -> int:
    return stats.outside_box + stats.nonfinite + stats.no_candidates + stats.beyond_gate + stats.unlabelled_nearest


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("candidates", ["labelled", "all"])
def test_hidden_points_and_gaussians_on_hidden_surfaces_match_brute_force(seed, candidates):
    """Hidden points are never candidates; the Gaussians of ``on_surface`` take their point's labels whatever the
    gate, the box and the candidates (fast path = reference; every ignored Gaussian counted once)."""
    from seggaussian.labels.occlusion import HiddenSurfaceHits

    rng = np.random.default_rng(seed)
    means, points, sem, inst, multi = _random_inputs(rng)
    hidden = rng.random(len(points)) < 0.3
    rows = np.sort(rng.choice(len(means), 40, replace=False))
    on_surface = HiddenSurfaceHits(rows, rng.choice(np.flatnonzero(hidden), 40), rng.uniform(0, 0.003, 40).astype(np.float32))
    config = TransferConfig(candidates=candidates, max_distance=0.05)
    fast = transfer_labels(means, points, sem, inst, multi, config, hidden=hidden, on_surface=on_surface)
    ref = transfer_labels_reference(means, points, sem, inst, multi, config, hidden=hidden, on_surface=on_surface)
    _assert_same(fast, ref)
    assert fast.stats.on_hidden_surface == 40 and fast.stats.num_candidates == (~hidden[
        np.flatnonzero(sem != IGNORE_LABEL) if candidates == "labelled" else np.arange(len(points))]).sum()
    np.testing.assert_array_equal(fast.semantic[rows], sem[on_surface.vertex])
    np.testing.assert_array_equal(fast.distances[rows], on_surface.distances)
    labelled_rows = rows[sem[on_surface.vertex] != IGNORE_LABEL]
    np.testing.assert_array_equal(fast.multilabel[labelled_rows], multi[on_surface.vertex[sem[on_surface.vertex] != IGNORE_LABEL]])
    others = np.setdiff1d(np.arange(len(means)), rows)
    plain = transfer_labels(means, points[~hidden], sem[~hidden], inst[~hidden], multi[~hidden], config)
    np.testing.assert_array_equal(fast.semantic[others], plain.semantic[others])  # the rest: hidden points dropped
    assert fast.stats.ignored == (fast.semantic == IGNORE_LABEL).sum() == _ignored_by_reason(fast.stats)


def test_on_surface_inputs_are_checked():
    from seggaussian.labels.occlusion import HiddenSurfaceHits

    means, points, sem, inst, _ = _random_inputs(np.random.default_rng(0), n=5, p=4)
    hits = lambda rows, vertex, d: HiddenSurfaceHits(np.array(rows), np.array(vertex), np.array(d, np.float32))
    for bad, message in ((hits([0, 0], [1, 2], [0, 0]), "distinct Gaussians"), (hits([7], [1], [0]), "distinct"),
                         (hits([1], [4], [0]), "vertex must index"), (hits([1], [2], [np.nan]), "finite"),
                         (hits([1, 2], [2], [0]), "equally long")):
        with pytest.raises(ValueError, match=message):
            transfer_labels(means, points, sem, inst, None, TransferConfig(), on_surface=bad)
    with pytest.raises(ValueError, match="hidden must be"):
        transfer_labels(means, points, sem, inst, None, TransferConfig(), hidden=np.zeros(3, bool))


def test_open3d_backend_matches_reference():
    pytest.importorskip("open3d")
    rng = np.random.default_rng(5)
    means, points, sem, inst, multi = _random_inputs(rng)
    config = TransferConfig(max_distance=0.1, backend="open3d")
    fast = transfer_labels(means, points, sem, inst, multi, config)
    ref = transfer_labels_reference(means, points, sem, inst, multi, config)
    _assert_same(fast, ref)


def test_unlabelled_nearest_point_gives_ignore_by_default():
    # The nearest point is unlabelled: by default (candidates="all") the Gaussian stays ignore, instance
    # and multilabel too; the labelled-only option gives the label of the next (labelled) point instead.
    points = np.array([[0.0, 0, 0], [0.05, 0, 0]])
    sem = np.array([IGNORE_LABEL, 7], np.int32)
    inst = np.array([5, 3], np.int32)  # an instance id on an unlabelled point must not survive either
    means = np.array([[0.01, 0, 0]])
    assert TransferConfig().candidates == "all"
    strict = transfer_labels(means, points, sem, inst, None, TransferConfig(max_distance=0.1))
    assert strict.semantic.tolist() == [IGNORE_LABEL] and strict.instance.tolist() == [IGNORE_LABEL]
    assert (strict.multilabel == IGNORE_LABEL).all() and strict.stats.unlabelled_nearest == 1
    assert strict.distances[0] == pytest.approx(0.01)
    lab = transfer_labels(means, points, sem, inst, None, TransferConfig(max_distance=0.1, candidates="labelled"))
    assert lab.semantic.tolist() == [7] and lab.instance.tolist() == [3]
    assert lab.distances[0] == pytest.approx(0.04)


def test_spacing_skips_exact_duplicates():
    # A 0.01 m grid where every point is repeated (as samples on shared mesh edges were): the median
    # spacing is still 0.01, not 0, in the fast estimate and in the brute-force reference.
    g = np.arange(0, 0.3, 0.01)
    grid = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)
    points = np.concatenate([grid, grid, grid[:100]])
    sem = np.zeros(len(points), np.int32)
    res = transfer_labels(np.zeros((1, 3)), points, sem, sem, config=TransferConfig(gate_min=0.001))
    ref = transfer_labels_reference(np.zeros((1, 3)), points, sem, sem, config=TransferConfig(gate_min=0.001))
    assert res.stats.spacing == pytest.approx(0.01, rel=1e-6)
    assert ref.stats.spacing == pytest.approx(0.01, rel=1e-6)
    assert res.stats.gate == pytest.approx(0.04, rel=1e-6)


def test_densified_mesh_has_no_duplicate_samples():
    # Two triangles sharing an edge, 4 steps per edge: the 3 inner samples of the shared edge appear once.
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    labels = np.array([1, 2, 3, 4])
    pts, (lab,) = densify_labelled_mesh(vertices, faces, 0.36, labels)  # ceil(sqrt(2) / 0.36) = 4 steps
    per_triangle = 15 - 3  # (n+1)(n+2)/2 grid points for n = 4, corners excluded
    assert len(pts) == 2 * per_triangle - 3
    assert len(np.unique(pts, axis=0)) == len(pts)
    assert lab.shape == (len(pts),)
    assert first_occurrences(np.array([[0.0, 1, 2], [-0.0, 1, 2], [1, 1, 2], [0, 1, 2]])).tolist() == [0, 2]


def test_gate_and_prefilter_count_what_they_remove():
    points = np.array([[0.0, 0, 0], [1.0, 1, 1]])
    sem = np.array([1, 2], np.int32)
    inst = np.array([10, 20], np.int32)
    means = np.array([
        [0.0, 0, 0.05],  # within gate of point 0
        [0.5, 0.5, 0.5],  # inside the box, beyond the gate (0.866 m)
        [1.2, 1.0, 1.0],  # inside box+margin (0.25), beyond gate 0.1 -> beyond_gate
        [3.0, 3.0, 3.0],  # outside the enlarged box: no query
        [np.nan, 0, 0],  # non-finite
        [np.inf, 0, 0],  # non-finite
    ])
    res = transfer_labels(means, points, sem, inst, None, TransferConfig(max_distance=0.1))
    assert res.semantic.tolist() == [1] + [IGNORE_LABEL] * 5
    assert res.instance.tolist() == [10] + [IGNORE_LABEL] * 5
    s = res.stats
    assert (s.beyond_gate, s.outside_box, s.nonfinite, s.no_candidates) == (2, 1, 2, 0)
    assert s.ignored == 5 and s.ignored_share == pytest.approx(5 / 6)
    assert res.distances[3] == DISTANCE_NOT_MEASURED and res.distances[4] == DISTANCE_NOT_MEASURED
    assert res.distances[2] == pytest.approx(0.2, abs=1e-6)
    assert np.isfinite(res.distances).all()
    assert s.class_histogram == {1: 1}


def test_prefilter_never_changes_labels_when_gate_exceeds_margin():
    # Gate 1.0 m > margin 0.25 m: the effective margin grows, so a point 0.6 m outside the box keeps its label.
    points = np.array([[0.0, 0, 0], [0.1, 0, 0]])
    res = transfer_labels(np.array([[0.7, 0, 0]]), points, np.array([3, 4]), np.array([0, 1]), None,
                          TransferConfig(max_distance=1.0))
    assert res.semantic.tolist() == [4] and res.stats.box_margin == pytest.approx(1.0)


@pytest.mark.parametrize("n,p", [(0, 10), (10, 0), (0, 0)])
def test_empty_inputs(n, p):
    rng = np.random.default_rng(0)
    means = rng.uniform(0, 1, (n, 3))
    points = rng.uniform(0, 1, (p, 3))
    res = transfer_labels(means, points, np.zeros(p, np.int32), np.zeros(p, np.int32))
    assert res.semantic.shape == (n,) and res.multilabel.shape == (n, 3) and res.distances.shape == (n,)
    assert (res.semantic == IGNORE_LABEL).all()
    assert res.stats.no_candidates == (n if p == 0 else 0)
    assert res.stats.ignored_share == (1.0 if n and not p else 0.0)
    ref = transfer_labels_reference(means, points, np.zeros(p, np.int32), np.zeros(p, np.int32))
    _assert_same(res, ref)


def test_all_points_unlabelled_counts_no_candidates():
    points = np.zeros((5, 3))
    labelled_only = TransferConfig(candidates="labelled")
    res = transfer_labels(np.zeros((3, 3)), points, np.full(5, IGNORE_LABEL), np.zeros(5), config=labelled_only)
    assert res.stats.num_candidates == 0 and res.stats.no_candidates == 3 and res.stats.ignored == 3
    every = transfer_labels(np.zeros((3, 3)), points, np.full(5, IGNORE_LABEL), np.zeros(5))  # default: all points
    assert every.stats.num_candidates == 5 and every.stats.unlabelled_nearest == 3 and every.stats.ignored == 3
    assert (every.instance == IGNORE_LABEL).all()


def test_bad_shapes_and_nan_points_raise_clear_errors():
    with pytest.raises(ValueError, match="gaussian_means"):
        transfer_labels(np.zeros((3, 2)), np.zeros((2, 3)), np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="semantic"):
        transfer_labels(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="NaN"):
        transfer_labels(np.zeros((3, 3)), np.array([[np.nan, 0, 0], [0, 0, 0]]), np.zeros(2), np.zeros(2))


def test_derived_gate_follows_point_spacing():
    # A 0.01 m grid: median spacing 0.01, gate = max(gate_min = 0.02, 4 * 0.01) = 0.04.
    g = np.arange(0, 0.5, 0.01)
    points = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)
    sem = np.zeros(len(points), np.int32)
    res = transfer_labels(np.array([[0.2, 0.2, 0.03], [0.2, 0.2, 0.05]]), points, sem, sem,
                          config=TransferConfig(gate_min=0.02))
    assert res.stats.gate == pytest.approx(0.04, rel=1e-6)
    floor = transfer_labels(np.array([[0.2, 0.2, 0.03]]), points, sem, sem)  # default floor wins
    assert floor.stats.gate == pytest.approx(TransferConfig().gate_min)
    assert res.stats.spacing == pytest.approx(0.01, rel=1e-6)
    assert res.stats.gate == pytest.approx(0.04, rel=1e-6)
    assert res.semantic.tolist() == [0, IGNORE_LABEL]
    ref = transfer_labels_reference(np.zeros((0, 3)), points, sem, sem)
    assert ref.stats.spacing == pytest.approx(res.stats.spacing)


def test_surface_labels_on_two_triangles():
    pytest.importorskip("open3d")
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    semantic = np.array([0, 1, 2, 3], np.int32)
    queries = np.array([[0.1, 0.1, 0.2], [0.9, 0.1, -0.1], [0.1, 0.85, 0.0], [0.95, 0.9, 0.05]])
    assert surface_labels(queries, vertices, faces, semantic).tolist() == [0, 1, 2, 3]
    acc = label_accuracy(np.array([0, 1, IGNORE_LABEL, 5]), np.array([0, 1, 2, IGNORE_LABEL]))
    assert acc == {"scored": 3, "correct": 2, "accuracy": 2 / 3}


# --- unlabelled objects on and against labelled surfaces -------------------------------------------------
FLOOR, WALL = 1, 0  # class ids of the labelled surfaces; everything else in the scene is unlabelled
GRID = 0.05  # metres between mesh vertices (a ScanNet++ mesh_aligned_0.05)


def _quad_grid(origin, u, v, label, grid=GRID):
    """Vertices [(m+1)(n+1), 3], triangles, labels of a planar rectangle ``origin + s u + t v`` meshed at ``grid``."""
    origin, u, v = (np.asarray(x, np.float64) for x in (origin, u, v))
    m = max(1, int(round(np.linalg.norm(u) / grid)))
    n = max(1, int(round(np.linalg.norm(v) / grid)))
    s, t = np.meshgrid(np.linspace(0, 1, m + 1), np.linspace(0, 1, n + 1), indexing="ij")
    verts = np.round(origin + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v, 9)  # exact copies where surfaces meet
    idx = np.arange((m + 1) * (n + 1)).reshape(m + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, tris, np.full(len(verts), label, np.int32)


def _contact_scene():
    """A floor and a wall (labelled) with a None-mapped rack standing on the floor against the wall, an
    out-of-vocabulary switch on the wall, and a masked patch of floor. Returns the mesh (vertices,
    triangles, semantic) and the visible surfaces to sample as (origin, u, v, normal, true label)."""
    rack_lo, rack_hi = np.array([0.0, 0.5, 0.0]), np.array([0.4, 1.0, 1.0])
    switch_lo, switch_hi = np.array([0.0, 1.5, 1.0]), np.array([0.01, 1.6, 1.1])
    parts = [
        _quad_grid([0, 0, 0], [2, 0, 0], [0, 2, 0], FLOOR),
        _quad_grid([0, 0, 0], [0, 2, 0], [0, 0, 2], WALL),
    ]
    surfaces = [((0, 0, 0), (2, 0, 0), (0, 2, 0), (0, 0, 1), FLOOR), ((0, 0, 0), (0, 2, 0), (0, 0, 2), (1, 0, 0), WALL)]
    for lo, hi in ((rack_lo, rack_hi), (switch_lo, switch_hi)):
        dx, dy, dz = hi - lo
        faces = [  # the visible faces (top, front, two sides); bottom and back touch floor and wall
            (lo + [0, 0, dz], (dx, 0, 0), (0, dy, 0), (0, 0, 1)),
            (lo + [dx, 0, 0], (0, dy, 0), (0, 0, dz), (1, 0, 0)),
            (lo, (dx, 0, 0), (0, 0, dz), (0, -1, 0)),
            (lo + [0, dy, 0], (dx, 0, 0), (0, 0, dz), (0, 1, 0)),
        ]
        for origin, u, v, normal in faces:
            parts.append(_quad_grid(origin, u, v, IGNORE_LABEL))
            surfaces.append((tuple(origin), u, v, normal, IGNORE_LABEL))
    vertices, triangles, semantic, offset = [], [], [], 0
    for verts, tris, labels in parts:
        vertices.append(verts)
        triangles.append(tris + offset)
        semantic.append(labels)
        offset += len(verts)
    vertices, semantic = np.concatenate(vertices), np.concatenate(semantic)
    masked = (np.abs(vertices[:, 2]) < 1e-9) & (vertices[:, 0] >= 1.2) & (vertices[:, 0] <= 1.6) & \
        (vertices[:, 1] >= 1.2) & (vertices[:, 1] <= 1.6)
    semantic[masked] = IGNORE_LABEL  # mesh_aligned_0.05_mask.txt
    occluders = [(rack_lo, rack_hi), (switch_lo, switch_hi)]
    return vertices, np.concatenate(triangles), semantic, surfaces, occluders


def _sample_surfaces(surfaces, occluders, rng, per_m2=4000, noise=0.003):
    """Gaussian centres on the visible surfaces, off the surface by N(0, noise) along the normal, and
    their true class (the floor's masked patch is ignore). Points hidden inside a box are dropped."""
    means, truth = [], []
    for origin, u, v, normal, label in surfaces:
        u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
        area = np.linalg.norm(np.cross(u, v))
        k = max(20, int(per_m2 * area))
        s, t = rng.random((k, 1)), rng.random((k, 1))
        p = np.asarray(origin, np.float64) + s * u + t * v
        inside = np.zeros(k, bool)
        for lo, hi in occluders:  # under the rack / behind the switch: not visible, no Gaussian
            inside |= ((p >= lo - 1e-9) & (p <= hi + 1e-9)).all(axis=1) & (label != IGNORE_LABEL)
        p = p[~inside] + rng.normal(0.0, noise, (int((~inside).sum()), 1)) * np.asarray(normal, np.float64)
        lab = np.full(len(p), label, np.int32)
        if label == FLOOR:
            lab[(p[:, 0] >= 1.2) & (p[:, 0] <= 1.6) & (p[:, 1] >= 1.2) & (p[:, 1] <= 1.6)] = IGNORE_LABEL
        means.append(p)
        truth.append(lab)
    return np.concatenate(means), np.concatenate(truth)


def test_unlabelled_objects_on_labelled_surfaces_stay_ignore():
    vertices, triangles, semantic, surfaces, occluders = _contact_scene()
    means, truth = _sample_surfaces(surfaces, occluders, np.random.default_rng(0))
    instance = np.where(semantic == IGNORE_LABEL, IGNORE_LABEL, semantic + 10).astype(np.int32)
    config = TransferConfig()
    samples, (s_sem, s_inst) = densify_labelled_mesh(vertices, triangles, config.mesh_sample_spacing, semantic, instance)
    points = np.concatenate([vertices, samples])
    sem, inst = np.concatenate([semantic, s_sem]), np.concatenate([instance, s_inst])
    default = transfer_labels(means, points, sem, inst, None, config)
    labelled_only = transfer_labels(means, points, sem, inst, None, TransferConfig(candidates="labelled"))

    unlabelled = truth == IGNORE_LABEL
    assert unlabelled.sum() > 1000
    kept = (default.semantic[unlabelled] == IGNORE_LABEL).mean()
    assert kept >= 0.98, f"only {kept:.4f} of the Gaussians on unlabelled surfaces stay ignore"
    assert (default.instance[unlabelled & (default.semantic == IGNORE_LABEL)] == IGNORE_LABEL).all()
    # the former default (labelled-only candidates) spills labels onto the rack, the switch and the patch
    # the labelled-only rule spills labels onto the rack, the switch and the patch (19% here; kept 98.3% above)
    assert (labelled_only.semantic[unlabelled] == IGNORE_LABEL).mean() < 0.9

    # labelled surfaces: no accuracy lost, except near contact vertices, shared by two differently labelled
    # surfaces (a copy of the vertex carries another label, or a triangle holds it with a differently
    # labelled corner). Labels are known per vertex, so within a grid cell's half diagonal of a contact
    # vertex the source does not say which surface a Gaussian belongs to.
    from scipy.spatial import cKDTree

    labels_at: dict = {}
    for coordinate, label in zip(map(tuple, vertices), semantic):
        labels_at.setdefault(coordinate, set()).add(int(label))
    contact = np.array([len(labels_at[c]) > 1 for c in map(tuple, vertices)])
    mixed = (semantic[triangles] != semantic[triangles[:, :1]]).any(axis=1)
    contact[np.unique(triangles[mixed])] = True
    near_contact, _ = cKDTree(vertices[contact]).query(means)
    shared = near_contact < GRID / np.sqrt(2.0)
    scored = ~unlabelled & ~shared
    acc_default = (default.semantic[scored] == truth[scored]).mean()
    acc_labelled = (labelled_only.semantic[scored] == truth[scored]).mean()
    assert acc_default >= acc_labelled, (acc_default, acc_labelled)
    assert acc_default >= 0.999
    # counted: the contact band holds 5.2% of the labelled Gaussians of this small, contact-rich scene;
    # inside it the default keeps 85% of them right (the rest go ignore), labelled-only 97%
    excepted = int((~unlabelled & shared).sum())
    assert 0 < excepted < 0.1 * int((~unlabelled).sum()), excepted
    # spacing of the densified mesh: real (not 0 from duplicated edge samples), so the gate is derived from it
    assert 0.0 < default.stats.spacing < GRID
