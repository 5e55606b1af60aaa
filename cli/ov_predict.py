"""``ovgaussian predict``: label every Gaussian of a scene against a free-text vocabulary."""

from __future__ import annotations

from pathlib import Path

import click

from cli._output import finish, guarded, json_option
from ovgaussian.bench_config import DEFAULT_MIN_ALPHA


@click.command("predict")
@click.argument("scene", type=click.Path(path_type=Path, dir_okay=False))
@click.option("--run", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Run folder of ovgaussian train.")
@click.option("--checkpoint", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="A checkpoint folder RUN/checkpoints/epoch-XXXX (default: the latest).")
@click.option("--vocab", required=True, help='Comma-separated class names, e.g. "chair, table, sofa".')
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="Labelled scene to write: PLY (int property 'semantic' = index into --vocab, class colours), "
                   "or .compressed.ply / .splat / .spz (class colours only; see --format).")
@click.option("--format", "output_format", type=click.Choice(["ply", "compressed_ply", "splat", "spz"]), default=None,
              help="Output format (default: from OUT's name; PLY otherwise).")
@click.option("--spz-version", type=click.Choice(["2", "3", "4"]), default="4", show_default=True,
              help="SPZ version written when the output is SPZ.")
@click.option("--color-by", "color_by", type=click.Choice(["semantic", "none"]), default="semantic", show_default=True,
              help="semantic: each Gaussian in its class's fixed palette colour (seggaussian/palette.py), higher SH "
                   "dropped, legend OUT.legend.json + OUT.legend.png written beside; none: keep the scene's colours.")
@click.option("--cameras", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help='JSON {"cameras": [{"name", "width", "height", "K", "viewmat" | "c2w"}]}: also write label-map PNGs.')
@click.option("--views-dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder of the label-map PNGs (default: OUT's name + '_views').")
@click.option("--colours", "colour_mode", type=click.Choice(["both", "f_dc", "rgb"]), default="both", show_default=True,
              help="Class colours in f_dc (SH colour, f_rest dropped), uchar red/green/blue properties, or both.")
@click.option("--on-invalid", type=click.Choice(["error", "drop", "repair"]), default="error", show_default=True,
              help="Invalid Gaussians in SCENE: fail, drop them (counted) or repair them (counted).")
@click.option("--min-alpha", type=float, default=DEFAULT_MIN_ALPHA, show_default=True,
              help="Label-map pixels with less accumulated alpha are left unlabelled.")
@json_option
@guarded
def command(scene, run, checkpoint, vocab, out, output_format, spz_version, color_by, cameras, views_dir, colour_mode,
            on_invalid, min_alpha, as_json):
    """Open-vocabulary segmentation of SCENE (3DGS PLY, compressed PLY, .splat or SPZ) with a trained run."""
    from ovgaussian.bench_config import PredictConfig
    from ovgaussian.predict import parse_vocabulary, run_predict

    names = parse_vocabulary(vocab)
    config = PredictConfig(run=run, checkpoint=checkpoint, vocabulary=names, colour_mode=colour_mode,
                           min_alpha=min_alpha, on_invalid=on_invalid, color_by=color_by,
                           output_format=output_format, spz_version=int(spz_version))
    report = run_predict(scene, out, config, cameras_path=cameras, views_dir=views_dir)
    shares = sorted(report.summary["shares"].items(), key=lambda kv: -kv[1])
    details = "\n".join(f"{name:>24s}  {100 * share:6.2f}%  ({report.summary['counts'][name]})" for name, share in shares)
    top = ", ".join(f"{n} {100 * s:.1f}%" for n, s in shares[:3])
    extra = f", {len(report.pngs)} PNGs" if report.pngs else ""
    extra += f", legend {report.legend[0]}" if report.legend else ""
    finish(f"predict: {report.summary['num_gaussians']} Gaussians labelled with {len(names)} classes "
           f"({top}) -> {out} ({report.format}){extra}", report.summary, as_json, details=details)
