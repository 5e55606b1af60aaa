"""``seggaussian synth``: write procedural rooms in the real ScanNet++ / Replica on-disk layouts."""

from __future__ import annotations

import math
import time
from pathlib import Path

import click

from cli._output import finish, guarded, json_option


@click.command("synth")
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="Raw tree to write (ScanNet++: a DATA_ROOT; Replica: one folder per room; both: OUT/scannetpp + OUT/replica).")
@click.option("--scenes", type=click.IntRange(min=0), default=9, show_default=True, help="Scenes to write (ScanNet++ scenes with --layout both).")
@click.option("--replica-scenes", type=click.IntRange(min=0), default=None,
              help="Replica rooms with --layout both (default: a third of --scenes, at least 1).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--layout", type=click.Choice(["scannetpp", "replica", "both"]), default="both", show_default=True)
@click.option("--width", type=click.IntRange(min=16), default=320, show_default=True,
              help="Image width (ScanNet++ height = 3/4 width; Replica keeps the NICE-SLAM 1200x680 aspect).")
@click.option("--height", type=click.IntRange(min=16), default=None,
              help="ScanNet++ image height (default: 3/4 of --width; 876 x 584 is ScanNet++'s undistorted DSLR size).")
@click.option("--views", type=click.IntRange(min=1), default=32, show_default=True, help="Views per scene.")
@click.option("--max-edge", type=click.FloatRange(min=0.005), default=0.05, show_default=True, help="Longest mesh edge (metres).")
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Processes writing scenes at once (the files do not depend on it).")
@click.option("--progress/--no-progress", default=True, show_default=True)
@json_option
@guarded
def command(out, scenes, replica_scenes, seed, layout, width, height, views, max_edge, jobs, progress, as_json) -> None:
    """Write synthetic furnished rooms (mesh, labels, cameras, RGB and ground-truth label images)."""
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    config = SynthConfig(width=width, height=height, num_views=views, max_edge=max_edge)
    if layout == "both":
        layouts = [("scannetpp", out / "scannetpp", scenes),
                   ("replica", out / "replica", replica_scenes if replica_scenes is not None else max(1, math.ceil(scenes / 3)))]
    else:
        layouts = [(layout, out, scenes)]
    show = progress and not as_json
    start = time.perf_counter()
    written: dict[str, list[str]] = {}
    for kind, root, count in layouts:
        report = (lambda i, name, kind=kind, count=count: click.echo(f"{kind} {i + 1}/{count}: {name}", err=True)) if show else None
        written[kind] = synthesize(root, count, seed, kind, config, progress=report, jobs=jobs)
    seconds = time.perf_counter() - start
    total = sum(len(v) for v in written.values())
    parts = ", ".join(f"{len(v)} {k}" for k, v in written.items())
    summary = f"synth: wrote {total} scene{'' if total == 1 else 's'} ({parts}) to {out} in {seconds:.1f} s (seed {seed})"
    finish(summary, {"out": str(out), "seed": seed, "scenes": written, "seconds": round(seconds, 3),
                     "width": width, "height": height, "views": views, "max_edge": max_edge}, as_json)
