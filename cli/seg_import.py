"""``seggaussian import SCENE --out DIR``: any splat file (PLY, compressed PLY, .splat, SPZ, .ksplat, glTF) -> validated
standard 3DGS PLY plus a JSON report."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import transform_options
from cli._output import finish, guarded, json_option


@click.command("import")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder: <stem>.ply (binary little endian, Inria layout) and <stem>.import.json.")
@click.option("--on-invalid", type=click.Choice(["error", "drop", "repair"]), default="error", show_default=True,
              help="Non-finite values, zero quaternions, overflowing log-scales, saturated opacity logits: "
                   "refuse, drop those rows, or repair them (see seggaussian/io/validate.py).")
@transform_options
@json_option
@guarded
def command(scene: Path, out_dir: Path, on_invalid: str, transform: str | None, from_frame: str | None,
            as_json: bool) -> None:
    """Read a splat file (3DGS PLY, compressed PLY, .splat, SPZ, .ksplat or glTF; detected by content), validate it,
    write a standard 3DGS PLY and a JSON report into OUT."""
    from seggaussian.frames.frame_config import FrameConfig
    from seggaussian.io.importing import ImportConfig, import_ply
    from seggaussian.io.splat_common import FORMAT_TITLES

    result = import_ply(scene, out_dir, ImportConfig(on_invalid=on_invalid, frame=FrameConfig(transform, from_frame)))
    report = result.report
    summary = (f"imported {result.num_gaussians} Gaussians (SH degree {result.sh_degree}) from {scene} "
               f"({FORMAT_TITLES[result.format]}) "
               f"-> {result.ply_path}; {report.describe_actions()}"
               + (f"; moved into the scene's frame by {result.frame['transform']}" if result.frame["transform"] else ""))
    payload = {"source": result.source, "format": result.format, "ply": result.ply_path, "report": result.report_path,
               "num_gaussians": result.num_gaussians, "sh_degree": result.sh_degree,
               "validation": report.to_dict(), "frame": result.frame}
    details = None if report.ok else f"found: {report.describe_issues()}"
    finish(summary, payload, as_json, details)
