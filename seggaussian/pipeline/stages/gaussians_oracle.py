"""gaussians stage, ``--gaussians oracle``: Gaussians sampled on the labelled mesh, with their true class."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.pipeline.config import BuildConfig
from seggaussian.core.gaussians import Gaussians
from seggaussian.labels.oracle import sample_oracle_gaussians
from seggaussian.core.scene import Scene
from seggaussian.util.seeds import scene_seed
from seggaussian.pipeline.stages.gaussians import save_gaussians


def run(scene: Scene, config: BuildConfig, scene_dir: Path, trained_ply: Path | None = None
        ) -> tuple[Gaussians, np.ndarray, dict]:
    """Sample, write ``gaussians_stage.parquet``; returns (Gaussians, truth ``[N]``, facts)."""
    rng = np.random.default_rng(scene_seed(config.oracle.seed + config.seed, scene.scene_id))
    g, truth = sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces, config.oracle, rng,
                                       tuple(v.camera for v in scene.views))
    save_gaussians(scene_dir, g, truth)
    return g, truth, {"mode": "oracle"}
