"""``ovgaussian train``: train OVGaussian on the train split of a dataset (options -> TrainConfig -> train)."""

from __future__ import annotations

from pathlib import Path

import click

from cli._output import finish, guarded, json_option
from ovgaussian.train_config import (
    DataConfig, LossConfig, OptimConfig, TeacherConfig, TextConfig, TrainConfig, field_help,
)

_T, _D, _X, _L, _O = (field_help(c) for c in (TrainConfig, DataConfig, TextConfig, LossConfig, OptimConfig))


@click.command("train")
@click.option("--data", "dataset", type=click.Path(path_type=Path, file_okay=False), required=True, help=_D["dataset"])
@click.option("--out", type=click.Path(path_type=Path, file_okay=False), required=True, help=_T["out"])
@click.option("--epochs", type=click.IntRange(min=1), default=TrainConfig.epochs, show_default=True, help=_T["epochs"])
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True, help=_T["device"])
@click.option("--batch-scenes", type=click.IntRange(min=1), default=TrainConfig.batch_scenes, show_default=True,
              help=_T["batch_scenes"])
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=OptimConfig.lr, show_default=True,
              help=_O["lr"])
@click.option("--schedule", type=click.Choice(["cosine", "poly", "constant"]), default=OptimConfig.schedule,
              show_default=True, help=_O["schedule"])
@click.option("--seed", type=int, default=TrainConfig.seed, show_default=True, help=_T["seed"])
@click.option("--resume", is_flag=True, help=_T["resume"])
@click.option("--no-adapter", is_flag=True, help="Ablation: train without the voxel-to-point adapter.")
@click.option("--no-3dt-align", is_flag=True, help=_L["no_3dt_align"])
@click.option("--no-vs-align", is_flag=True, help=_L["no_vs_align"])
@click.option("--classes", "num_classes", type=click.Choice(["20", "50", "100"]), default="20", show_default=True,
              help=_D["num_classes"])
@click.option("--text-encoder", type=click.Choice(["minilm", "clip"]), default="minilm", show_default=True,
              help=_X["encoder"])
@click.option("--clip-model", type=click.Path(path_type=Path, file_okay=False), default=None, help=_X["clip_model"])
@click.option("--model-preset", type=click.Choice(["default", "slim"]), default="default", show_default=True,
              help=_T["model_preset"])
@click.option("--pixels-per-view", type=click.IntRange(min=1), default=None, help=_D["pixels_per_view"])
@click.option("--temperature", type=click.FloatRange(min=0, min_open=True), default=LossConfig.temperature,
              show_default=True, help=_L["temperature"])
@click.option("--verify", is_flag=True, help=_D["verify"])
@click.option("--progress/--no-progress", default=True, show_default=True, help=_T["progress"])
@json_option
@guarded
def command(dataset, out, epochs, device, batch_scenes, lr, schedule, seed, resume, no_adapter, no_3dt_align,
            no_vs_align, num_classes, text_encoder, clip_model, model_preset, pixels_per_view, temperature, verify,
            progress, as_json):
    """Train the OVGaussian network (GSR + CCL) on the train split of DATASET into the run folder OUT.

    Several processes: torchrun --nproc-per-node=P -m cli.ovgaussian_cli train ... (global batch unchanged).
    """

    config = TrainConfig(
        out=out, epochs=epochs, batch_scenes=batch_scenes, seed=seed, device=device, resume=resume,
        model_preset=model_preset, use_adapter=not no_adapter, progress=progress and not as_json,
        data=DataConfig(dataset=dataset, num_classes=int(num_classes), pixels_per_view=pixels_per_view,
                        verify=verify),
        text=TextConfig(encoder=text_encoder, clip_model=clip_model),
        teacher=TeacherConfig(clip_model=clip_model),
        loss=LossConfig(temperature=temperature, no_3dt_align=no_3dt_align, no_vs_align=no_vs_align),
        optim=OptimConfig(lr=lr, schedule=schedule),
    )
    from ovgaussian.train import train

    result = train(config)
    m = result.last_epoch_metrics
    skipped = sum(result.skipped.values())
    summary = (f"trained {result.epochs} epochs ({result.steps} steps) on {result.num_scenes} scenes"
               f" ({skipped} skipped): loss {m.get('loss', float('nan')):.4f} -> {result.checkpoint}")
    payload = {"run": str(result.run_dir), "epochs": result.epochs, "steps": result.steps,
               "metrics": m, "skipped": result.skipped, "scenes": result.num_scenes,
               "checkpoint": None if result.checkpoint is None else str(result.checkpoint),
               "notes": list(result.notes)}
    finish(summary, payload, as_json, details="\n".join(result.notes) or None)
