"""``seggaussian build``: raw scenes -> labelled 3DGS Parquet shards (incremental, content-keyed cache)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from cli._output import finish, guarded, json_option


@click.command("build")
@click.option("--source", type=click.Choice(["synthetic", "scannetpp", "replica", "ply"]), default="synthetic",
              show_default=True, help="Raw tree kind. synthetic = ROOT/scannetpp + ROOT/replica from `seggaussian synth`.")
@click.option("--root", type=click.Path(path_type=Path), required=True, help="Raw tree (read only).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Dataset folder to create or update.")
@click.option("--scenes", multiple=True, help="Scene ids to build (repeat or comma-separate); default all.")
@click.option("--jobs", type=int, default=1, show_default=True, help="Scenes built in parallel.")
@click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True)
@click.option("--address", default=None, help="Ray cluster address (with --executor ray).")
@click.option("--fit", "fit_mode", type=click.Choice(["auto", "always", "never"]), default="auto", show_default=True,
              help="auto: fit only scenes without a trained PLY.")
@click.option("--gaussians", "gaussians_mode", type=click.Choice(["fit", "oracle"]), default="fit", show_default=True,
              help="oracle: sample Gaussians on the labelled mesh (fast, exact geometry).")
@click.option("--ply-dir", type=click.Path(path_type=Path), default=None,
              help="Trained PLYs: <scene>.ply or <scene>/point_cloud/iteration_*/point_cloud.ply.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--gate", type=float, default=None, help="Label-transfer distance gate in metres (default: 4 x point spacing).")
@click.option("--oracle-gaussians", type=int, default=None, help="Gaussians per scene with --gaussians oracle.")
@click.option("--fit-iterations", type=int, default=None, help="Fitting iterations per scene.")
@click.option("--max-image-side", type=int, default=None, help="Longest side of stored views (pixels, 0 = source size).")
@click.option("--view-stride", type=int, default=None, help="Keep every n-th train view (novel views always kept).")
@click.option("--keep-going", is_flag=True,
              help="Exit 0 even when scenes failed (a failed scene built before keeps its last good copy).")
@click.option("--progress/--no-progress", default=True, show_default=True)
@json_option
@guarded
def command(source, root, out, scenes, jobs, executor, address, fit_mode, gaussians_mode, ply_dir, seed, gate,
            oracle_gaussians, fit_iterations, max_image_side, view_stride, keep_going, progress, as_json) -> None:
    """Build or update a labelled 3DGS dataset: Gaussians, label transfer, per-view label maps, shards, split."""
    from seggaussian.build import build_dataset, summary_table
    from seggaussian.build_config import BuildConfig

    config = BuildConfig(source=source, root=root, out=out, jobs=jobs, executor=executor, address=address,
                         fit=fit_mode, gaussians=gaussians_mode, ply_dir=ply_dir, seed=seed,
                         progress=progress and not as_json,
                         scenes=tuple(s for item in scenes for s in item.split(",") if s) or None)
    if gate is not None:
        config = replace(config, transfer=replace(config.transfer, max_distance=gate))
    if oracle_gaussians is not None:
        config = replace(config, oracle=replace(config.oracle, num_gaussians=oracle_gaussians))
    if fit_iterations is not None:
        config = replace(config, fit_config=config.fit_config.with_iterations(fit_iterations))
    if max_image_side is not None:
        config = replace(config, views=replace(config.views, max_image_side=max_image_side))
    if view_stride is not None:
        config = replace(config, views=replace(config.views, view_stride=view_stride))
    report = build_dataset(config)
    c = report.counts
    summary = (f"built {c['built']}, skipped {c['skipped']} (cached), failed {c['failed']} scenes -> {report.dataset} "
               f"({report.split_counts.get('train', 0)} train / {report.split_counts.get('val', 0)} val / "
               f"{report.split_counts.get('xval', 0)} xval; {report.files} files, {report.bytes} bytes"
               f"{'' if report.assembled else ', shards unchanged'}) in {report.seconds:.1f} s")
    payload = {
        "dataset": str(report.dataset),
        "counts": c,
        "splits": report.split_counts,
        "files": report.files,
        "bytes": report.bytes,
        "assembled": report.assembled,
        "synthesized": report.synthesized,
        "seconds": report.seconds,
        "kept_last_good": list(report.kept),
        "swept_temps": report.swept,
        "scenes": [{"scene": o.scene_id, "source": o.domain, "status": o.status, "stages_run": list(o.stages_run),
                    "reason": o.reason, "seconds": o.seconds, **o.info} for o in report.outcomes],
    }
    for scene_id in report.kept:
        click.echo(f"warning: scene {scene_id} failed to build; the shards keep its last good copy", err=True)
    finish(summary, payload, as_json, summary_table(report))
    if c["failed"] and not keep_going:
        raise SystemExit(1)
