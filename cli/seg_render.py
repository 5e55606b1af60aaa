"""``seggaussian render SCENE.ply --out OUT.png [--camera CAM.json | --look-at]``: a quick look at a 3DGS scene."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import transform_options
from cli._output import finish, guarded, json_option


@click.command("render")
@click.argument("ply", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="PNG to write.")
@click.option("--camera", "camera_json", type=click.Path(dir_okay=False, path_type=Path),
              help="JSON with K (3x3), viewmat (4x4 world-to-camera, OpenCV), width, height.")
@click.option("--look-at", "look_at", is_flag=True,
              help="Orbit camera looking at the scene centre (the default when --camera is not given).")
@click.option("--width", type=click.IntRange(min=1), default=640, show_default=True, help="Orbit camera width.")
@click.option("--height", type=click.IntRange(min=1), default=480, show_default=True, help="Orbit camera height.")
@click.option("--azimuth", type=float, default=-60.0, show_default=True, help="Orbit camera azimuth (deg, z up).")
@click.option("--elevation", type=float, default=30.0, show_default=True, help="Orbit camera elevation (deg).")
@click.option("--fov", type=click.FloatRange(1.0, 170.0), default=60.0, show_default=True,
              help="Orbit camera horizontal field of view (deg).")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=None, help="SH bands to use (default: all).")
@click.option("--background", type=(float, float, float), default=(0.0, 0.0, 0.0), show_default=True,
              help="Background RGB in [0, 1].")
@click.option("--backend", type=click.Choice(["auto", "fast", "reference"]), default="auto", show_default=True)
@transform_options
@json_option
@guarded
def command(ply, out, camera_json, look_at, width, height, azimuth, elevation, fov, sh_degree, background, backend,
            transform, from_frame, as_json) -> None:
    """Render one view of a splat file (3DGS PLY, compressed PLY, .splat, SPZ, .ksplat or glTF) to a PNG."""
    from seggaussian.frames.frame_config import FrameConfig
    from seggaussian.render.quicklook import QuicklookConfig, render_ply_view

    if camera_json and look_at:
        raise click.UsageError("give either --camera or --look-at, not both")
    config = QuicklookConfig(ply=ply, out=out, camera_json=camera_json, width=width, height=height,
                             azimuth_deg=azimuth, elevation_deg=elevation, fov_deg=fov, sh_degree=sh_degree,
                             background=tuple(background), backend=backend,
                             frame=FrameConfig(transform, from_frame))
    info = render_ply_view(config)
    summary = (f"{out}: {info['num_gaussians']} Gaussians rendered at {info['width']}x{info['height']} "
               f"(SH degree {info['sh_degree']}, {100 * info['covered_fraction']:.1f}% covered) "
               f"in {info['seconds']:.2f} s")
    finish(summary, info, as_json)
