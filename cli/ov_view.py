"""``ovgaussian view``: open-vocabulary queries of a scene in the browser (viser), or ``--export`` a shareable file."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import config_option, transform_options
from cli._output import finish, guarded, json_option
from ovgaussian.view.config import DEFAULT_HOST, DEFAULT_PORT, MODES, ViewConfig
from ovgaussian.view.relevancy import DEFAULT_THRESHOLD


@click.command("view")
@click.argument("scene", type=click.Path(path_type=Path, dir_okay=False), required=False)
@config_option(ViewConfig, "run", "--run", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(ViewConfig, "checkpoint", "--checkpoint", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(ViewConfig, "dataset", "--dataset", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(ViewConfig, "scene_id", "--scene", "scene_id", default=None, metavar="ID")
@config_option(ViewConfig, "cameras", "--cameras", type=click.Path(path_type=Path, dir_okay=False), default=None)
@config_option(ViewConfig, "vocabulary", "--vocab", "vocab", default=None)
@config_option(ViewConfig, "queries", "--query", "query", default="")
@config_option(ViewConfig, "mode", "--mode", type=click.Choice(MODES), default=None)
@config_option(ViewConfig, "threshold", "--threshold", type=click.FloatRange(0.0, 1.0), default=DEFAULT_THRESHOLD,
               show_default=True)
@config_option(ViewConfig, "calibrate", "--calibrate/--no-calibrate", default=True, show_default=True)
@config_option(ViewConfig, "host", "--host", default=DEFAULT_HOST, show_default=True)
@config_option(ViewConfig, "port", "--port", type=click.IntRange(0, 65535), default=DEFAULT_PORT, show_default=True)
@config_option(ViewConfig, "export", "--export", type=click.Path(path_type=Path, dir_okay=False), default=None)
@config_option(ViewConfig, "on_invalid", "--on-invalid", type=click.Choice(["error", "drop", "repair"]),
               default="error", show_default=True)
@config_option(ViewConfig, "device", "--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@transform_options
@json_option
@guarded
def command(scene, run, checkpoint, dataset, scene_id, cameras, vocab, query, mode, threshold, calibrate, host, port,
            export, on_invalid, device, transform, from_frame, as_json):
    """Query SCENE (any splat format) with free text in the browser: RGB, ground-truth, predicted-label and
    query modes, click a Gaussian to inspect it. Serves until Ctrl-C; --export writes a file and exits."""
    from ovgaussian.predict.query import parse_vocabulary
    from ovgaussian.view.session import run_view
    from seggaussian.frames.frame_config import FrameConfig

    config = ViewConfig(scene=scene, run=run, checkpoint=checkpoint, dataset=dataset, scene_id=scene_id,
                        cameras=cameras, vocabulary=parse_vocabulary(vocab) if vocab else (), queries=query, mode=mode,
                        threshold=threshold, calibrate=calibrate, host=host, port=port, export=export,
                        frame=FrameConfig(transform, from_frame), on_invalid=on_invalid, device=device)

    def say(message: str) -> None:  # progress: stderr under --json, so stdout stays one JSON document
        click.echo(message, err=as_json)

    def ready(viewer) -> None:
        say(f"view: open {viewer.url} in a browser (Ctrl-C to stop)")

    report = run_view(config, progress=say, on_ready=ready)
    summary = report.summary
    if report.export is not None:
        finish(f"view: {summary['num_gaussians']} Gaussians ({summary['mode']}) exported to {report.export} "
               f"({summary['export_bytes']:,} bytes)", summary, as_json)
        return
    finish(f"view: served {summary['num_gaussians']} Gaussians at {summary['url']} for "
           f"{summary['served_seconds']:.0f} s (last mode {summary['mode']})", summary, as_json)
