"""gaussians stage, ``--gaussians scan``: a scan turned into splats, one isotropic Gaussian per mesh vertex.

What a user gets from a scanner or from a point cloud dropped into a splat viewer: every vertex of the scene's
mesh becomes a Gaussian at the vertex (or a seeded uniform draw of the vertices, ``--scan-max-gaussians``: a sparser
scanner), with the vertex colour as its DC term (no higher SH bands), an isotropic scale as 3DGS initializes from
points (the mean distance to the ``SCAN_NEIGHBOURS`` nearest other kept vertices) and a solid opacity
``SCAN_OPACITY``. No fitting and no sampling: a cheap rendition of a room for training across
renditions (``ovgaussian train --rendition-data``) and for scoring a model on splats it was not trained on. Labels
come from the transfer stage like any splat's (each Gaussian lies on its vertex, so it keeps the vertex's label).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.core.scene import Scene
from seggaussian.fit.config import FitConfig
from seggaussian.fit.initialize import initialize_gaussians
from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.stages.gaussians import save_gaussians

#: Opacity of a scan's Gaussians (a scanned point is solid).
SCAN_OPACITY = 0.99
#: Nearest other vertices whose mean distance sets a Gaussian's scale (3DGS's initialization from points: 3).
SCAN_NEIGHBOURS = 3


def scan_settings(vertices: int, max_gaussians: int | None = None) -> FitConfig:
    """The point-initialization settings of a scan: no voxel averaging, DC colour only, every vertex kept (or a
    uniform draw of ``max_gaussians`` of them when there are more: ``initialize_gaussians`` draws only then)."""
    cap = vertices if max_gaussians is None else max_gaussians
    return replace(FitConfig(), init_voxel_size=0.0, max_gaussians=max(1, cap), init_opacity=SCAN_OPACITY,
                   init_knn=SCAN_NEIGHBOURS, sh_degree=0)


def run(scene: Scene, config: BuildConfig, scene_dir: Path, trained_ply: Path | None = None
        ) -> tuple[Gaussians, None, dict]:
    """One Gaussian per vertex (or per drawn vertex, ``BuildConfig.scan_max_gaussians``), write
    ``gaussians_stage.parquet``; returns (Gaussians, None, facts)."""
    settings = scan_settings(len(scene.points), config.scan_max_gaussians)
    gaussians, _ = initialize_gaussians(scene.points, scene.colors, settings, rng=np.random.default_rng(config.seed))
    save_gaussians(scene_dir, gaussians, None)
    facts = {"mode": "scan"}
    if len(gaussians) < len(scene.points):
        facts["scan_vertices"] = len(scene.points)
    return gaussians, None, facts
