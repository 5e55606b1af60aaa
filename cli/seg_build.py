"""``seggaussian build``: raw scenes -> labelled 3DGS Parquet shards (incremental, content-keyed cache)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from seggaussian.pipeline.config import BuildConfig, ViewConfig
from seggaussian.labels.config import OracleConfig, TransferConfig
from cli.seg_fit import PRESET_HELP
from seggaussian.fit.config import PRESETS, FitConfig


@click.command("build")
@config_option(BuildConfig, "source", "--source", type=click.Choice(["synthetic", "scannetpp", "replica", "ply"]),
               default="synthetic", show_default=True)
@config_option(BuildConfig, "root", "--root", type=click.Path(path_type=Path), required=True)
@config_option(BuildConfig, "out", "--out", type=click.Path(path_type=Path), required=True)
@click.option("--scenes", multiple=True, help="Scene ids to build (repeat or comma-separate); default all.")
@config_option(BuildConfig, "jobs", "--jobs", type=int, default=1, show_default=True)
@config_option(BuildConfig, "executor", "--executor", type=click.Choice(["local", "ray"]), default="local",
               show_default=True)
@config_option(BuildConfig, "address", "--address", default=None)
@config_option(BuildConfig, "ray_cpus", "--ray-cpus", type=click.FloatRange(min=0, min_open=True), default=1.0,
               show_default=True)
@config_option(BuildConfig, "ray_memory_gb", "--ray-memory-gb", type=click.FloatRange(min=0), default=2.0,
               show_default=True)
@config_option(BuildConfig, "ray_retries", "--ray-retries", type=click.IntRange(min=0), default=3, show_default=True)
@config_option(BuildConfig, "ray_timeout", "--ray-timeout", type=click.FloatRange(min=0, min_open=True), default=60.0,
               show_default=True)
@config_option(BuildConfig, "ray_scene_timeout", "--ray-scene-timeout", type=click.FloatRange(min=0), default=0.0,
               show_default=True)
@config_option(BuildConfig, "num_shards", "--num-shards", type=click.IntRange(min=1), default=1, show_default=True)
@config_option(BuildConfig, "shard_index", "--shard-index", type=click.IntRange(min=0), default=0, show_default=True)
@config_option(BuildConfig, "fit", "--fit", "fit_mode", type=click.Choice(["auto", "always", "never"]), default="auto",
               show_default=True)
@config_option(BuildConfig, "gaussians", "--gaussians", "gaussians_mode", type=click.Choice(["fit", "oracle", "scan"]),
               default="fit", show_default=True)
@config_option(BuildConfig, "ply_dir", "--ply-dir", type=click.Path(path_type=Path), default=None)
@config_option(BuildConfig, "seed", "--seed", type=int, default=0, show_default=True)
@config_option(TransferConfig, "max_distance", "--gate", type=float, default=None)
@config_option(TransferConfig, "occlusion_tolerance", "--occlusion-tolerance", type=click.FloatRange(min=0), default=None)
@click.option("--keep-occluded", is_flag=True,
              help="Let label points that the train views look at but never see give labels too (the wall behind a "
                   "window); by default they give none.")
@config_option(OracleConfig, "num_gaussians", "--oracle-gaussians", type=int, default=None)
@config_option(BuildConfig, "scan_max_gaussians", "--scan-max-gaussians", type=click.IntRange(min=1), default=None)
@click.option("--fit-preset", type=click.Choice(PRESETS), default="default", show_default=True, help=PRESET_HELP)
@config_option(FitConfig, "iterations", "--fit-iterations", type=int, default=None)
@config_option(FitConfig, "max_gaussians", "--fit-max-gaussians", type=click.IntRange(min=1), default=None)
@config_option(ViewConfig, "max_image_side", "--max-image-side", type=int, default=None)
@config_option(ViewConfig, "view_stride", "--view-stride", type=int, default=None)
@click.option("--keep-going", is_flag=True,
              help="Exit 0 even when scenes failed (a failed scene built before keeps its last good copy).")
@config_option(BuildConfig, "progress", "--progress/--no-progress", default=True, show_default=True)
@json_option
@guarded
def command(source, root, out, scenes, jobs, executor, address, ray_cpus, ray_memory_gb, ray_retries, ray_timeout,
            ray_scene_timeout, num_shards, shard_index, fit_mode, gaussians_mode, ply_dir, seed, gate,
            occlusion_tolerance, keep_occluded, oracle_gaussians, scan_max_gaussians, fit_preset, fit_iterations,
            fit_max_gaussians, max_image_side, view_stride, keep_going, progress, as_json) -> None:
    """Build or update a labelled 3DGS dataset: Gaussians, label transfer, per-view label maps, shards, split."""
    from seggaussian.pipeline.dataset import build_dataset, summary_table

    config = BuildConfig(source=source, root=root, out=out, jobs=jobs, executor=executor, address=address,
                         ray_cpus=ray_cpus, ray_memory_gb=ray_memory_gb, ray_retries=ray_retries,
                         ray_timeout=ray_timeout, ray_scene_timeout=ray_scene_timeout, num_shards=num_shards,
                         shard_index=shard_index,
                         fit=fit_mode, gaussians=gaussians_mode, scan_max_gaussians=scan_max_gaussians,
                         ply_dir=ply_dir, seed=seed,
                         progress=progress and not as_json,
                         scenes=tuple(s for item in scenes for s in item.split(",") if s) or None)
    if gate is not None:
        config = replace(config, transfer=replace(config.transfer, max_distance=gate))
    if keep_occluded and occlusion_tolerance is not None:
        raise click.UsageError("--keep-occluded and --occlusion-tolerance exclude each other")
    if keep_occluded or occlusion_tolerance is not None:
        config = replace(config, transfer=replace(config.transfer,
                                                  occlusion_tolerance=None if keep_occluded else occlusion_tolerance))
    if oracle_gaussians is not None:
        config = replace(config, oracle=replace(config.oracle, num_gaussians=oracle_gaussians))
    if fit_preset != "default":
        config = replace(config, fit_config=FitConfig.preset(fit_preset))
    if fit_iterations is not None:
        config = replace(config, fit_config=config.fit_config.with_iterations(fit_iterations))
    if fit_max_gaussians is not None:
        config = replace(config, fit_config=replace(config.fit_config, max_gaussians=fit_max_gaussians))
    if max_image_side is not None:
        config = replace(config, views=replace(config.views, max_image_side=max_image_side))
    if view_stride is not None:
        config = replace(config, views=replace(config.views, view_stride=view_stride))
    report = build_dataset(config)
    c = report.counts
    if report.shard is not None:
        summary = (f"slice {report.shard[0]} of {report.shard[1]}: built {c['built']}, skipped {c['skipped']} "
                   f"(cached), failed {c['failed']} scenes -> {report.dataset} (not assembled: a build without "
                   f"--num-shards assembles every slice) in {report.seconds:.1f} s")
    else:
        summary = (f"built {c['built']}, skipped {c['skipped']} (cached), failed {c['failed']} scenes -> "
                   f"{report.dataset} ({report.split_counts.get('train', 0)} train / "
                   f"{report.split_counts.get('val', 0)} val / {report.split_counts.get('xval', 0)} xval; "
                   f"{report.files} files, {report.bytes} bytes{'' if report.assembled else ', shards unchanged'}) "
                   f"in {report.seconds:.1f} s")
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
        "cpu_seconds": report.cpu_seconds,
        "shard": None if report.shard is None else {"index": report.shard[0], "count": report.shard[1]},
        "ray_nodes": [{"node_id": n.node_id, "address": n.address} for n in report.nodes],
        "scenes": [{"scene": o.scene_id, "source": o.domain, "status": o.status, "stages_run": list(o.stages_run),
                    "reason": o.reason, "seconds": o.seconds, "cpu_seconds": o.cpu_seconds, **o.info}
                   for o in report.outcomes],
    }
    for scene_id in report.kept:
        click.echo(f"warning: scene {scene_id} failed to build; the shards keep its last good copy", err=True)
    finish(summary, payload, as_json, summary_table(report))
    if c["failed"] and not keep_going:
        raise SystemExit(1)
