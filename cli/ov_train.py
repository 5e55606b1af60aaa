"""``ovgaussian train``: train OVGaussian on the train split of a dataset (options -> TrainConfig -> train)."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from ovgaussian.run.config import DataConfig, LossConfig, OptimConfig, TeacherConfig, TextConfig, TrainConfig


@click.command("train")
@config_option(DataConfig, "dataset", "--data", "dataset", type=click.Path(path_type=Path, file_okay=False),
               required=True)
@config_option(TrainConfig, "out", "--out", type=click.Path(path_type=Path, file_okay=False), required=True)
@config_option(TrainConfig, "epochs", "--epochs", type=click.IntRange(min=1), default=TrainConfig.epochs,
               show_default=True)
@config_option(TrainConfig, "device", "--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@config_option(TrainConfig, "batch_scenes", "--batch-scenes", type=click.IntRange(min=1),
               default=TrainConfig.batch_scenes, show_default=True)
@config_option(OptimConfig, "lr", "--lr", type=click.FloatRange(min=0, min_open=True), default=OptimConfig.lr,
               show_default=True)
@config_option(OptimConfig, "schedule", "--schedule", type=click.Choice(["cosine", "poly", "constant"]),
               default=OptimConfig.schedule, show_default=True)
@config_option(TrainConfig, "seed", "--seed", type=int, default=TrainConfig.seed, show_default=True)
@config_option(TrainConfig, "resume", "--resume", type=click.Choice(["always", "auto"]), is_flag=False,
               flag_value="always", default=None, metavar="[auto]")
@click.option("--no-adapter", is_flag=True, help="Ablation: train without the voxel-to-point adapter.")
@config_option(LossConfig, "no_3dt_align", "--no-3dt-align", is_flag=True)
@config_option(LossConfig, "no_vs_align", "--no-vs-align", is_flag=True)
@config_option(DataConfig, "num_classes", "--classes", "num_classes", type=click.Choice(["20", "50", "100"]),
               default="20", show_default=True)
@config_option(TextConfig, "encoder", "--text-encoder", type=click.Choice(["minilm", "clip"]), default="minilm",
               show_default=True)
@config_option(TextConfig, "clip_model", "--clip-model", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(TrainConfig, "model_preset", "--model-preset", type=click.Choice(["default", "slim"]), default="default",
               show_default=True)
@config_option(DataConfig, "pixels_per_view", "--pixels-per-view", type=click.IntRange(min=1), default=None)
@config_option(DataConfig, "loss_gaussians", "--loss-gaussians", type=click.IntRange(min=1), default=None)
@config_option(TrainConfig, "voxel_size", "--voxel-size", type=click.FloatRange(min=0, min_open=True), default=None)
@config_option(TrainConfig, "use_coordinates", "--use-coordinates/--no-coordinates", default=TrainConfig.use_coordinates,
               show_default=True)
@config_option(TrainConfig, "input_encoding", "--input-encoding", type=click.Choice(["robust", "invariant", "raw"]),
               default=TrainConfig.input_encoding, show_default=True)
@config_option(TrainConfig, "pool_weighting", "--pool-weighting", type=click.Choice(["opacity", "mean"]),
               default=TrainConfig.pool_weighting, show_default=True)
@config_option(TrainConfig, "devoxelize", "--devoxelize", type=click.Choice(["nearest", "trilinear"]),
               default=TrainConfig.devoxelize, show_default=True)
@config_option(TrainConfig, "surface_radius", "--surface-radius", type=click.FloatRange(min=0),
               default=TrainConfig.surface_radius, show_default=True, metavar="METRES")
@config_option(TrainConfig, "grid_anchor", "--grid-anchor", type=click.Choice(["min", "lattice"]),
               default=TrainConfig.grid_anchor, show_default=True)
@config_option(TrainConfig, "voxel_geometry", "--voxel-geometry/--no-voxel-geometry",
               default=TrainConfig.voxel_geometry, show_default=True)
@config_option(LossConfig, "class_balance", "--class-balance", type=click.FloatRange(min=0),
               default=LossConfig.class_balance, show_default=True)
@config_option(LossConfig, "lovasz_weight", "--lovasz-weight", type=click.FloatRange(min=0),
               default=LossConfig.lovasz_weight, show_default=True)
@config_option(LossConfig, "opacity_power", "--opacity-power", type=click.FloatRange(min=0),
               default=LossConfig.opacity_power, show_default=True)
@config_option(LossConfig, "unlabelled_as_unseen", "--unlabelled-as-unseen", is_flag=True)
@config_option(LossConfig, "unlabelled_weight", "--unlabelled-weight", type=click.FloatRange(min=0),
               default=LossConfig.unlabelled_weight, show_default=True)
@config_option(LossConfig, "temperature", "--temperature", type=click.FloatRange(min=0, min_open=True),
               default=LossConfig.temperature, show_default=True)
@config_option(DataConfig, "holdout_classes", "--holdout-classes", type=str, default="")
@config_option(DataConfig, "splat_augment", "--splat-augment", is_flag=True)
@config_option(DataConfig, "rendition_augment", "--rendition-augment", is_flag=True)
@config_option(DataConfig, "off_surface_augment", "--off-surface-augment", is_flag=True)
@config_option(DataConfig, "colour_augment", "--colour-augment", is_flag=True)
@config_option(DataConfig, "renditions", "--rendition-data", "renditions", multiple=True,
               type=click.Path(path_type=Path, file_okay=False, exists=True), metavar="DATASET")
@config_option(DataConfig, "verify", "--verify", is_flag=True)
@config_option(DataConfig, "scene_cache_size", "--scene-cache-size", type=click.IntRange(min=1),
               default=DataConfig.scene_cache_size, show_default=True, metavar="N")
@config_option(TrainConfig, "keep_checkpoints", "--keep-checkpoints", type=click.IntRange(min=0),
               default=TrainConfig.keep_checkpoints, show_default=True)
@config_option(TrainConfig, "threads", "--threads", type=click.IntRange(min=1), default=None)
@config_option(TrainConfig, "loader_workers", "--loader-workers", type=click.IntRange(min=0),
               default=TrainConfig.loader_workers, show_default=True, metavar="N")
@config_option(TrainConfig, "progress", "--progress/--no-progress", default=True, show_default=True)
@json_option
@guarded
def command(dataset, out, epochs, device, batch_scenes, lr, schedule, seed, resume, no_adapter, no_3dt_align,
            no_vs_align, num_classes, text_encoder, clip_model, model_preset, pixels_per_view, loss_gaussians,
            voxel_size,
            use_coordinates, input_encoding, pool_weighting, devoxelize, grid_anchor, surface_radius, voxel_geometry,
            class_balance, lovasz_weight,
            opacity_power, unlabelled_as_unseen, unlabelled_weight, temperature, holdout_classes,
            splat_augment, rendition_augment, off_surface_augment, colour_augment, renditions, verify, scene_cache_size,
            keep_checkpoints,
            threads, loader_workers, progress, as_json):
    """Train the OVGaussian network (GSR + CCL) on the train split of DATASET into the run folder OUT.

    Several processes: torchrun --nproc-per-node=P -m cli.ovgaussian_cli train ... (global batch unchanged).
    """

    config = TrainConfig(
        out=out, epochs=epochs, batch_scenes=batch_scenes, seed=seed, device=device,
        resume="auto" if resume == "auto" else resume is not None,
        model_preset=model_preset, use_adapter=not no_adapter, progress=progress and not as_json,
        voxel_size=voxel_size, use_coordinates=use_coordinates, input_encoding=input_encoding,
        pool_weighting=pool_weighting, devoxelize=devoxelize, grid_anchor=grid_anchor, surface_radius=surface_radius,
        voxel_geometry=voxel_geometry,
        keep_checkpoints=keep_checkpoints, threads=threads, loader_workers=loader_workers,
        data=DataConfig(dataset=dataset, num_classes=int(num_classes), pixels_per_view=pixels_per_view,
                        loss_gaussians=loss_gaussians,
                        holdout_classes=tuple(n.strip() for n in holdout_classes.split(",") if n.strip()),
                        splat_augment=splat_augment, rendition_augment=rendition_augment,
                        off_surface_augment=off_surface_augment, colour_augment=colour_augment,
                        renditions=tuple(renditions), verify=verify,
                        scene_cache_size=scene_cache_size),
        text=TextConfig(encoder=text_encoder, clip_model=clip_model),
        teacher=TeacherConfig(clip_model=clip_model),
        loss=LossConfig(temperature=temperature, no_3dt_align=no_3dt_align, no_vs_align=no_vs_align,
                        class_balance=class_balance, lovasz_weight=lovasz_weight, opacity_power=opacity_power,
                        unlabelled_as_unseen=unlabelled_as_unseen,
                        unlabelled_weight=unlabelled_weight),
        optim=OptimConfig(lr=lr, schedule=schedule),
    )
    from ovgaussian.train.loop import phase_line, train

    result = train(config)
    if result.rank != 0:  # under torchrun the summary is rank 0's: the others have no checkpoint to name
        return
    m = result.last_epoch_metrics
    skipped = sum(result.skipped.values())
    summary = (f"trained {result.epochs} epochs ({result.steps} steps) on {result.num_scenes} scenes"
               f" ({skipped} skipped): loss {m.get('loss', float('nan')):.4f} -> {result.checkpoint}"
               f"; {phase_line(result.phases)}")
    payload = {"run": str(result.run_dir), "epochs": result.epochs, "steps": result.steps,
               "metrics": m, "skipped": result.skipped, "scenes": result.num_scenes,
               "checkpoint": None if result.checkpoint is None else str(result.checkpoint),
               "notes": list(result.notes), "phases": result.phases}
    finish(summary, payload, as_json, details="\n".join(result.notes) or None)
