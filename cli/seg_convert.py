"""``seggaussian convert IN OUT``: any splat file (format detected by content) to the format OUT's name asks for."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import config_option, transform_options
from cli._output import finish, guarded, json_option
from seggaussian.io.converting import ConvertConfig


@click.command("convert")
@click.argument("source", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
@config_option(ConvertConfig, "on_invalid", "--on-invalid", type=click.Choice(["error", "drop", "repair"]),
               default="error", show_default=True)
@config_option(ConvertConfig, "drop", "--drop", is_flag=True)
@config_option(ConvertConfig, "spz_version", "--spz-version", type=click.Choice(["2", "3", "4"]), default="3",
               show_default=True)
@config_option(ConvertConfig, "gltf_compression", "--gltf-compression", type=click.Choice(["none", "spz"]),
               default="none", show_default=True)
@transform_options
@json_option
@guarded
def command(source: Path, out: Path, on_invalid: str, drop: bool, spz_version: str, gltf_compression: str,
            transform: str | None, from_frame: str | None, as_json: bool) -> None:
    """Convert SOURCE (3DGS PLY, compressed PLY, .splat, SPZ, .ksplat or glTF; detected by content) to OUT, whose
    name picks the format: .ply, .compressed.ply, .splat, .spz, .ksplat, .glb or .gltf (KHR_gaussian_splatting).
    What OUT's format cannot hold (SH bands, labels) is refused unless --drop."""
    from seggaussian.frames.frame_config import FrameConfig
    from seggaussian.io.converting import convert_splat
    from seggaussian.io.splat_common import FORMAT_TITLES

    config = ConvertConfig(on_invalid=on_invalid, drop=drop, spz_version=int(spz_version),
                           gltf_compression=gltf_compression, frame=FrameConfig(transform, from_frame))
    result = convert_splat(source, out, config)
    report = result.report
    dropped = result.dropped
    parts = []
    if "sh_degree" in dropped:
        parts.append(f"SH degree {dropped['sh_degree'][0]} cut to {dropped['sh_degree'][1]}")
    if "extras" in dropped:
        parts.append(f"columns {', '.join(dropped['extras'])} dropped")
    summary = (f"converted {result.num_gaussians} Gaussians (SH degree {result.sh_degree}) from {source} "
               f"({FORMAT_TITLES[result.in_format]}) -> {out} ({FORMAT_TITLES[result.out_format]}); "
               f"{report.describe_actions()}"
               + (f"; --drop: {', '.join(parts)}" if parts else "")
               + (f"; moved by {result.frame['transform']}" if result.frame["transform"] else ""))
    payload = {"source": result.source, "out": result.out, "in_format": result.in_format,
               "out_format": result.out_format, "num_gaussians": result.num_gaussians, "sh_degree": result.sh_degree,
               "dropped": dropped, "validation": report.to_dict(), "frame": result.frame}
    details = None if report.ok else f"found: {report.describe_issues()}"
    finish(summary, payload, as_json, details)
