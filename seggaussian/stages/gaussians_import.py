"""gaussians stage, import mode: a trained 3DGS file (any format io.formats reads) read as is (its labels, if any, come from the transfer)."""

from __future__ import annotations

from pathlib import Path

from seggaussian.build_config import BuildConfig
from seggaussian.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians
from seggaussian.scene import Scene
from seggaussian.stages.gaussians import save_gaussians


def run(scene: Scene, config: BuildConfig, scene_dir: Path, trained_ply: Path | None = None
        ) -> tuple[Gaussians, None, dict]:
    """Read ``trained_ply``, write ``gaussians.npz``; returns (Gaussians, None, facts)."""
    g, _report, _format = read_gaussians(trained_ply)
    g = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)  # labels come from the transfer
    save_gaussians(scene_dir, g, None)
    return g, None, {"mode": "import", "ply": str(trained_ply)}
