"""``seggaussian align SPLAT --to MESH_OR_SCENE --out TRANSFORM.json``: the similarity that puts a splat exported in a
trainer's own frame onto its scene's mesh, written for ``--transform`` (never applied silently)."""

from __future__ import annotations

from pathlib import Path

import click

from cli._output import finish, guarded, json_option


@click.command("align")
@click.argument("splat", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--to", "to", required=True, type=click.Path(path_type=Path),
              help="The scene's mesh (or point cloud) as a PLY file, or a raw tree folder with --scene.")
@click.option("--scene", "scene_id", default=None,
              help="Scene id inside the raw tree --to (ScanNet++ id, Replica room).")
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="TRANSFORM.json to write: {\"world_from_splat\": 4x4, ...}, for --transform or "
                   "<scene>.transform.json.")
@json_option
@guarded
def command(splat: Path, to: Path, scene_id: str | None, out: Path, as_json: bool) -> None:
    """Register SPLAT (any splat format) onto the mesh of --to (rotation, translation, uniform scale: coarse FPFH +
    RANSAC, then scaled ICP; see seggaussian/align/registration.py) and write the transform. Refuses, writing nothing, when the
    aligned Gaussians do not reach the build's placement thresholds."""
    from seggaussian.align.registration import run_align

    result, payload = run_align(splat, to, out, scene_id)
    where = f"{to} scene {scene_id}" if scene_id else str(to)
    summary = (f"aligned {splat} onto {where}: scale {result.scale:.4g}, residual {100 * result.residual_m:.2f} cm, "
               f"fitness {result.fitness:.3f}, "
               f"{100 * result.placement.on_mesh_share:.1f} % of the opacity on the mesh, "
               f"{100 * result.placement.surface_covered_share:.1f} % of its surface covered "
               f"({result.seconds:.1f} s) -> {out}; use it with --transform {out}")
    finish(summary, dict(payload, out=str(out)), as_json)
