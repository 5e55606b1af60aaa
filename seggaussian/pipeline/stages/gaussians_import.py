"""gaussians stage, import mode: a trained 3DGS file (any format io.formats reads), moved into the scene's frame by
its ``<scene>.transform.json`` when one lies beside it (its labels, if any, come from the transfer)."""

from __future__ import annotations

from pathlib import Path

from seggaussian.pipeline.config import BuildConfig
from seggaussian.frames.frame_config import FrameConfig, frame_record, to_scene_frame
from seggaussian.frames.transform_spec import resolve_transform
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians
from seggaussian.core.scene import Scene
from seggaussian.pipeline.stages.gaussians import save_gaussians


def frame_key(transform_file: Path | None) -> dict:
    """What the stage's output depends on of the splat's frame: the resolved ``world_from_splat`` (so an edit of the
    transform file, or of the COLMAP model a ``gsplat:`` spec reads, reruns the stage), or None."""
    if transform_file is None:
        return {"transform": None}
    frame = resolve_transform(str(transform_file), None)
    return {"transform": str(transform_file), "world_from_splat": [[round(float(v), 12) for v in row]
                                                                   for row in frame.world_from_splat.matrix]}


def run(scene: Scene, config: BuildConfig, scene_dir: Path, trained_ply: Path | None = None,
        transform_file: Path | None = None) -> tuple[Gaussians, None, dict]:
    """Read ``trained_ply``, move it by ``transform_file`` (if any), write ``gaussians_stage.parquet``; returns
    (Gaussians, None, facts with the frame record)."""
    g, _report, _format = read_gaussians(trained_ply)
    g = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)  # labels come from the transfer
    g, frame = to_scene_frame(g, FrameConfig(str(transform_file) if transform_file else None))
    save_gaussians(scene_dir, g, None)
    return g, None, {"mode": "import", "ply": str(trained_ply), "frame": frame_record(frame)}
