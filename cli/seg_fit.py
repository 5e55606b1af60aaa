"""``seggaussian fit --source ... --root RAW --scene ID --out SCENE.ply``: fit 3D Gaussians to one scene on the CPU."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from seggaussian.fit.config import PRESETS, FitConfig

#: Help of ``--preset`` / ``seggaussian build --fit-preset``.
PRESET_HELP = ("FitConfig to start from: `default` (FitConfig()) or `profile` (FitConfig.profile(): the ~37 s CPU "
               "fit of a 160x120 profile room, depth from the mesh, no opacity reset). Other fit options override it.")


@click.command("fit")
@click.option("--source", type=click.Choice(["synthetic", "scannetpp", "replica"]), default="synthetic",
              show_default=True, help="Raw tree kind (synthetic = output of `seggaussian synth`).")
@click.option("--root", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Raw tree.")
@click.option("--scene", "scene_id", required=True, help="Scene id.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="PLY to write; metrics go to SCENE.fit.json next to it.")
@click.option("--preset", type=click.Choice(PRESETS), default="default", show_default=True, help=PRESET_HELP)
@config_option(FitConfig, "iterations", "--iterations", type=int, default=None)
@config_option(FitConfig, "downscale", "--downscale", type=float, default=None)
@config_option(FitConfig, "max_gaussians", "--max-gaussians", type=int, default=None)
@config_option(FitConfig, "sh_degree", "--sh-degree", type=int, default=None)
@config_option(FitConfig, "time_budget_seconds", "--time-budget", type=float, default=None)
@config_option(FitConfig, "opacity_reset", "--opacity-reset/--no-opacity-reset", default=None)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--progress/--no-progress", default=True, show_default=True)
@json_option
@guarded
def command(source, root, scene_id, out, preset, iterations, downscale, max_gaussians, sh_degree, time_budget,
            opacity_reset, seed, progress, as_json) -> None:
    """Fit a scene's train views (novel views held out for PSNR/SSIM) and write SCENE.ply + SCENE.fit.json.

    Unset options keep the FitConfig default; --iterations scales the densification/reset schedule with it."""
    from seggaussian.fit.optimize import fit_to_ply, metrics_path

    overrides = {"downscale": downscale, "max_gaussians": max_gaussians, "sh_degree": sh_degree,
                 "time_budget_seconds": time_budget, "opacity_reset": opacity_reset}
    config = FitConfig.preset(preset)
    if iterations is not None:  # the whole schedule scales with the number of iterations
        config = config.with_iterations(iterations)
    config = replace(config, **{k: v for k, v in overrides.items() if v is not None})
    result = fit_to_ply(source, root, scene_id, out, config, seed=seed, progress=progress and not as_json)
    m = result.metrics
    psnr = "n/a" if m["novel_psnr"] is None else f"{m['novel_psnr']:.2f} dB"
    ssim = "n/a" if m["novel_ssim"] is None else f"{m['novel_ssim']:.3f}"
    summary = (f"{out}: scene {scene_id}, {m['gaussians']} Gaussians, {m['iterations']} iterations in "
               f"{m['seconds']:.1f} s, novel-view PSNR {psnr}, SSIM {ssim} ({m['early_stop_reason']})")
    payload = {k: v for k, v in m.items() if k != "densification"}
    finish(summary, dict(payload, ply=str(out), metrics_json=str(metrics_path(out))), as_json)
