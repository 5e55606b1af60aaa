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


def test_every_vertex_becomes_a_solid_isotropic_gaussian_with_its_colour_and_label(scan_build):
    raw, out = scan_build
    (scene_id,) = scannetpp.list_scenes(raw / "scannetpp")
    scene = scannetpp.read_scene(raw / "scannetpp", scene_id)
    split = shards.read_manifest(out)["scenes"][scene_id]["split"]
    g = shards.read_scene(out, split, scene_id, views=False).gaussians
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
