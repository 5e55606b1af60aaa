"""gaussians stage, fitting mode: 3DGS fitted to the scene's views (``seggaussian.fit.optimize``)."""

from __future__ import annotations

from pathlib import Path

from seggaussian.pipeline.config import BuildConfig
from seggaussian.fit.optimize import fit_scene
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.scene import Scene
from seggaussian.util.seeds import scene_seed
from seggaussian.pipeline.stages.gaussians import save_gaussians

#: Fit metrics copied into the manifest.
REPORTED_METRICS = ("novel_psnr", "novel_ssim", "novel_l1", "iterations", "early_stop_reason")


def run(scene: Scene, config: BuildConfig, scene_dir: Path, trained_ply: Path | None = None
        ) -> tuple[Gaussians, None, dict]:
    """Fit, write ``gaussians_stage.parquet``; returns (Gaussians, None, facts with the fit metrics)."""
    result = fit_scene(scene, config.fit_config, seed=scene_seed(config.seed, scene.scene_id) % 2**31,
                       progress=config.progress and config.jobs == 1)
    metrics = {k: v for k, v in result.metrics.items() if k in REPORTED_METRICS}
    save_gaussians(scene_dir, result.gaussians, None)
    return result.gaussians, None, {"mode": "fit", "fit_metrics": metrics}
