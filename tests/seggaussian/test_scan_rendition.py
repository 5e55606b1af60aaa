"""``seggaussian build --gaussians scan``: a scan turned into splats, one isotropic Gaussian per mesh vertex, built
like any splat (labels through the transfer stage) and checked against the mesh it came from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from seggaussian import shards
from seggaussian.core.constants import SH_C0
from seggaussian.pipeline import dataset as build_mod
from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.stages.gaussians_scan import SCAN_NEIGHBOURS, SCAN_OPACITY
from seggaussian.sources import scannetpp

synthetic = pytest.importorskip("seggaussian.sources.synthetic.generate")


@pytest.fixture(scope="module")
def scan_build(tmp_path_factory) -> tuple[Path, Path]:
    raw = tmp_path_factory.mktemp("raw")
    synthetic.synthesize(raw / "scannetpp", 1, 3, "scannetpp", synthetic.SynthConfig(width=48, num_views=4))
    out = tmp_path_factory.mktemp("ds") / "dataset"
    report = build_mod.build_dataset(BuildConfig(source="synthetic", root=raw, out=out, gaussians="scan",
                                                 progress=False))
    assert [o.status for o in report.outcomes] == ["built"], [o.reason for o in report.outcomes]
    return raw, out


def _gaussians(dataset: Path, scene_id: str):
    """The built Gaussians of ``scene_id`` (whichever split holds it)."""
    split = shards.read_manifest(dataset)["scenes"][scene_id]["split"]
    return shards.read_scene(dataset, split, scene_id, views=False).gaussians


def test_every_vertex_becomes_a_solid_isotropic_gaussian_with_its_colour_and_label(scan_build):
    raw, out = scan_build
    (scene_id,) = scannetpp.list_scenes(raw / "scannetpp")
    scene = scannetpp.read_scene(raw / "scannetpp", scene_id)
    g = _gaussians(out, scene_id)
    points = np.asarray(scene.points, np.float64)
    assert len(g) == len(points)
    np.testing.assert_allclose(g.means, points, atol=1e-6)  # one per vertex, in vertex order
    np.testing.assert_allclose(g.sh[:, 0] * SH_C0 + 0.5, np.asarray(scene.colors) / 255.0, atol=1e-5)
    assert g.sh.shape[1] == 1  # the DC term only
    np.testing.assert_allclose(1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64))), SCAN_OPACITY, rtol=1e-5)
    assert np.ptp(g.log_scales, axis=1).max() < 1e-6  # isotropic
    # scale: the mean distance to the nearest other vertices (brute force on a subset)
    rows = np.random.default_rng(0).choice(len(points), 50, replace=False)
    for i in rows:
        d = np.sort(np.linalg.norm(points - points[i], axis=1))[1:SCAN_NEIGHBOURS + 1]
        assert float(np.exp(g.log_scales[i, 0])) == pytest.approx(max(d.mean(), 1e-7), rel=1e-4)
    # every Gaussian keeps its vertex's label (ignore stays ignore), whether or not a view sees the vertex; a
    # vertex that shares its position with a vertex of another label may take either
    labels = g.extras["semantic"]
    vertex = np.asarray(scene.semantic)
    wrong = np.flatnonzero(labels != vertex)
    _, first, counts = np.unique(points, axis=0, return_inverse=True, return_counts=True)
    shared = counts[first.reshape(-1)] > 1
    assert shared[wrong].all(), wrong[~shared[wrong]][:10]
    assert wrong.size <= 0.001 * len(points)


def test_a_capped_scan_is_a_seeded_draw_of_vertices_scaled_by_their_own_spacing(scan_build, tmp_path):
    """``--scan-max-gaussians``: a sparser scanner. Every Gaussian is a distinct vertex with its colour and label,
    its scale the mean distance to the nearest other *kept* vertices, and the draw follows the seed."""
    raw, full = scan_build
    (scene_id,) = scannetpp.list_scenes(raw / "scannetpp")
    scene = scannetpp.read_scene(raw / "scannetpp", scene_id)
    points = np.asarray(scene.points, np.float64)
    cap = len(points) // 4

    def capped(out: Path, seed: int):
        report = build_mod.build_dataset(BuildConfig(source="synthetic", root=raw, out=out, gaussians="scan",
                                                     scan_max_gaussians=cap, seed=seed, progress=False))
        assert [o.status for o in report.outcomes] == ["built"], [o.reason for o in report.outcomes]
        return _gaussians(out, scene_id)

    g = capped(tmp_path / "a", 0)
    assert len(g) == cap
    # every Gaussian sits on a vertex, no position more often than the mesh has it (vertices may share a position)
    positions, first, counts = np.unique(points, axis=0, return_index=True, return_counts=True)
    drawn, drawn_counts = np.unique(g.means.astype(np.float64), axis=0, return_counts=True)
    at = np.searchsorted(positions.view([("", positions.dtype)] * 3).ravel(),
                         drawn.view([("", drawn.dtype)] * 3).ravel())
    np.testing.assert_array_equal(positions[at], drawn)
    assert (drawn_counts <= counts[at]).all()
    index = {tuple(p): i for p, i, c in zip(positions, first, counts) if c == 1}  # vertices alone at their place
    alone = np.array([tuple(m) in index for m in g.means.astype(np.float64)])
    assert alone.mean() > 0.5
    rows = np.array([index[tuple(m)] for m in g.means[alone].astype(np.float64)])
    np.testing.assert_allclose(g.sh[alone, 0] * SH_C0 + 0.5, np.asarray(scene.colors)[rows] / 255.0, atol=1e-5)
    np.testing.assert_array_equal(g.extras["semantic"][alone], np.asarray(scene.semantic)[rows])
    kept = g.means.astype(np.float64)
    for i in np.random.default_rng(1).choice(cap, 30, replace=False):
        d = np.sort(np.linalg.norm(kept - kept[i], axis=1))[1:SCAN_NEIGHBOURS + 1]
        assert float(np.exp(g.log_scales[i, 0])) == pytest.approx(max(d.mean(), 1e-7), rel=1e-4)
    full_scale = np.median(_gaussians(full, scene_id).log_scales[:, 0])
    assert np.median(g.log_scales[:, 0]) > full_scale + np.log(1.2)  # sparser vertices, larger Gaussians
    np.testing.assert_array_equal(capped(tmp_path / "b", 0).means, g.means)  # seeded
    assert not np.array_equal(capped(tmp_path / "c", 1).means, g.means)
