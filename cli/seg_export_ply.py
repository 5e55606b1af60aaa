"""``seggaussian export-ply DATASET --scene ID --out labelled.ply``: one scene as a labelled 3DGS PLY."""

from __future__ import annotations

from pathlib import Path

import click

from cli._output import finish, guarded, json_option


@click.command("export-ply")
@click.argument("dataset", type=click.Path(file_okay=False, path_type=Path))
@click.option("--scene", "scene_id", required=True, help="Scene id.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="PLY to write.")
@click.option("--color-by", "color_by", type=click.Choice(["semantic", "instance"]), default=None,
              help="Paint each Gaussian in its label's fixed palette colour (seggaussian/labels/palette.py; higher SH "
                   "zeroed, labels kept) and write OUT.legend.json + OUT.legend.png beside it.")
@json_option
@guarded
def command(dataset: Path, scene_id: str, out: Path, color_by: str | None, as_json: bool) -> None:
    """Write a scene's Gaussians with semantic, instance (int) and transfer_distance vertex properties."""
    from seggaussian.pipeline.export import export_scene_ply

    info = export_scene_ply(dataset, scene_id, out, color_by=color_by)
    summary = (f"{out}: scene {scene_id} ({info['split']}), {info['gaussians']} Gaussians, "
               f"{info['labelled']} labelled"
               + (f", coloured by {color_by} (legend {info['legend'][0]})" if color_by else ""))
    finish(summary, info, as_json)
