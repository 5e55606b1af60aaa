"""Label transfer: KD-tree fast path against the brute-force reference, gate/prefilter accounting, empties."""

from __future__ import annotations

import numpy as np
import pytest

from seggaussian.build_config import TransferConfig
from seggaussian.constants import IGNORE_LABEL
from seggaussian.transfer import (
    DISTANCE_NOT_MEASURED,
    densify_labelled_mesh,
    first_occurrences,
    label_accuracy,
    surface_labels,
    transfer_labels,
    transfer_labels_reference,
)


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
    for key in ("outside_box", "nonfinite", "no_candidates", "beyond_gate", "unlabelled_nearest", "ignored"):
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
