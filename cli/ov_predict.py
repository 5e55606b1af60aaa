"""``ovgaussian predict``: label every Gaussian of a scene against a free-text vocabulary."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from ovgaussian.predict.config import DEFAULT_MIN_ALPHA
from ovgaussian.predict.config import PredictConfig


@click.command("predict")
@click.argument("scene", type=click.Path(path_type=Path, dir_okay=False))
@config_option(PredictConfig, "run", "--run", type=click.Path(path_type=Path, file_okay=False), required=True)
@config_option(PredictConfig, "checkpoint", "--checkpoint", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(PredictConfig, "ensemble_runs", "--ensemble-run", "ensemble_runs", multiple=True,
               type=click.Path(path_type=Path, file_okay=False))
@click.option("--vocab", required=True, help='Comma-separated class names, e.g. "chair, table, sofa".')
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="Labelled scene to write: PLY (int property 'semantic' = index into --vocab, class colours), "
                   ".glb / .gltf (KHR_gaussian_splatting; labels as the _SEMANTIC attribute, the vocabulary in the "
                   "file's extras), or .compressed.ply / .splat / .spz / .ksplat (class colours only; see --format).")
@config_option(PredictConfig, "output_format", "--format", "output_format",
               type=click.Choice(["ply", "compressed_ply", "splat", "spz", "ksplat", "gltf"]), default=None)
@config_option(PredictConfig, "spz_version", "--spz-version", type=click.Choice(["2", "3", "4"]), default="3",
               show_default=True)
@config_option(PredictConfig, "color_by", "--color-by", "color_by", type=click.Choice(["semantic", "none"]),
               default="semantic", show_default=True)
@click.option("--cameras", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help='JSON {"cameras": [{"name", "width", "height", "K", "viewmat" | "c2w"}]}: also write label-map PNGs.')
@click.option("--views-dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of the label-map PNGs (default: OUT's name + '_views').")
@config_option(PredictConfig, "colour_mode", "--colours", "colour_mode", type=click.Choice(["both", "f_dc", "rgb"]),
               default="both", show_default=True)
@config_option(PredictConfig, "on_invalid", "--on-invalid", type=click.Choice(["error", "drop", "repair"]),
               default="error", show_default=True)
@config_option(PredictConfig, "prompt_ensemble", "--prompt-ensemble", is_flag=True)
@config_option(PredictConfig, "stacking_gamma", "--stacking-gamma", type=click.FloatRange(min=0), default=0.0,
               show_default=True)
@config_option(PredictConfig, "class_offsets", "--class-offsets", type=click.Path(path_type=Path, dir_okay=False),
               default=None)
@config_option(PredictConfig, "faint_neighbours", "--faint-neighbours", type=click.IntRange(min=0), default=0,
               show_default=True)
@config_option(PredictConfig, "min_alpha", "--min-alpha", type=float, default=DEFAULT_MIN_ALPHA, show_default=True)
@config_option(PredictConfig, "device", "--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@json_option
@guarded
def command(scene, run, checkpoint, ensemble_runs, vocab, out, output_format, spz_version, color_by, cameras, views_dir,
            colour_mode, on_invalid, prompt_ensemble, stacking_gamma, class_offsets, faint_neighbours, min_alpha, device,
            as_json):
    """Open-vocabulary segmentation of SCENE (3DGS PLY, compressed PLY, .splat, SPZ or .ksplat) with a trained run."""
    from ovgaussian.predict.query import parse_vocabulary, run_predict

    names = parse_vocabulary(vocab)
    config = PredictConfig(run=run, checkpoint=checkpoint, ensemble_runs=tuple(ensemble_runs), vocabulary=names,
                           colour_mode=colour_mode, min_alpha=min_alpha, on_invalid=on_invalid, color_by=color_by,
                           output_format=output_format, spz_version=int(spz_version),
                           prompt_ensemble=prompt_ensemble, stacking_gamma=stacking_gamma, class_offsets=class_offsets,
                           faint_neighbours=faint_neighbours, device=device)
    report = run_predict(scene, out, config, cameras_path=cameras, views_dir=views_dir)
    shares = sorted(report.summary["shares"].items(), key=lambda kv: -kv[1])
    details = "\n".join(f"{name:>24s}  {100 * share:6.2f}%  ({report.summary['counts'][name]})" for name, share in shares)
    top = ", ".join(f"{n} {100 * s:.1f}%" for n, s in shares[:3])
    extra = f", {len(report.pngs)} PNGs" if report.pngs else ""
    extra += f", legend {report.legend[0]}" if report.legend else ""
    finish(f"predict: {report.summary['num_gaussians']} Gaussians labelled with {len(names)} classes "
           f"({top}) -> {out} ({report.format}){extra}", report.summary, as_json, details=details)
