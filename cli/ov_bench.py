"""``ovgaussian bench``: Table-1 mIoU (3D CSA, OVA, CDA | 2D CSA, OVA, NVA, CDA) of a run or a baseline."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from ovgaussian.bench.config import BenchConfig, METRICS
from ovgaussian.predict.config import DEFAULT_MIN_ALPHA


@click.command("bench")
@config_option(BenchConfig, "dataset", "--data", "dataset", type=click.Path(path_type=Path, file_okay=False), required=True)
@config_option(BenchConfig, "run", "--run", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(BenchConfig, "checkpoint", "--checkpoint", type=click.Path(path_type=Path, file_okay=False), default=None)
@config_option(BenchConfig, "predictor", "--predictor", type=click.Choice(["model", "majority", "nearest-colour"]),
               default="model", show_default=True)
@config_option(BenchConfig, "prompt_ensemble", "--prompt-ensemble", is_flag=True)
@config_option(BenchConfig, "class_offsets", "--class-offsets", is_flag=True)
@config_option(BenchConfig, "generative", "--generative", is_flag=True)
@config_option(BenchConfig, "faint_neighbours", "--faint-neighbours", type=click.IntRange(min=0), default=0,
               show_default=True)
@config_option(BenchConfig, "ensemble_runs", "--ensemble-run", "ensemble_runs",
               type=click.Path(path_type=Path, file_okay=False), multiple=True)
@config_option(BenchConfig, "stacking_run", "--stacking-run", type=click.Path(path_type=Path, file_okay=False),
               default=None)
@click.option("--metric", "metric", type=click.Choice([*METRICS, "all"], case_sensitive=False), default="all",
              show_default=True, help="Metric to compute.")
@config_option(BenchConfig, "num_classes", "--classes", "num_classes", type=click.Choice(["20", "50", "100"]),
               default="20", show_default=True)
@click.option("--dim", type=click.Choice(["3d", "2d", "both"]), default="both", show_default=True,
              help="Score on the Gaussians (3d), on rendered label maps (2d), or both.")
@config_option(BenchConfig, "min_alpha", "--min-alpha", type=float, default=DEFAULT_MIN_ALPHA, show_default=True)
@config_option(BenchConfig, "max_views_per_scene", "--max-views", type=int, default=None)
@config_option(BenchConfig, "max_scenes", "--max-scenes", type=int, default=None)
@click.option("--out", "out", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="JSON report path (default: RUN/bench-K<classes>.json, or DATA/bench-<predictor>-K<classes>.json).")
@click.option("--label", default=None, help="Row label of the printed table (default: the run folder or predictor).")
@config_option(BenchConfig, "verify", "--verify", is_flag=True)
@config_option(BenchConfig, "device", "--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@config_option(BenchConfig, "progress", "--progress/--no-progress", default=True, show_default=True)
@json_option
@guarded
def command(dataset, run, checkpoint, predictor, prompt_ensemble, class_offsets, generative, faint_neighbours,
            ensemble_runs, stacking_run, metric, num_classes, dim, min_alpha, max_views, max_scenes,
            out, label, verify, device, progress, as_json):
    """Benchmark a trained run (or a baseline) on the val / train-novel / xval scenes of a dataset."""
    from ovgaussian.bench.evaluate import run_bench, table1_header, table1_row
    from seggaussian.util.atomic import write_json_atomic

    metrics = METRICS if metric.lower() == "all" else (metric.upper(),)
    dims = ("3d", "2d") if dim == "both" else (dim,)
    if predictor == "model" and run is None:
        raise click.UsageError("--run is required with --predictor model")
    config = BenchConfig(dataset=dataset, run=run, checkpoint=checkpoint, predictor=predictor,
                         prompt_ensemble=prompt_ensemble, class_offsets=class_offsets, generative=generative,
                         faint_neighbours=faint_neighbours,
                         stacking_run=stacking_run, ensemble_runs=tuple(ensemble_runs),
                         metrics=metrics,
                         dims=dims, num_classes=int(num_classes), min_alpha=min_alpha, max_views_per_scene=max_views,
                         max_scenes=max_scenes, progress=progress and not as_json, verify=verify, device=device)
    report = run_bench(config)
    if out is None:
        out = (run / f"bench-K{num_classes}.json") if predictor == "model" else \
            (dataset / f"bench-{predictor}-K{num_classes}.json")
    write_json_atomic(out, report.payload)
    row_label = label or (run.name if predictor == "model" else predictor)
    table = table1_header() + "\n" + table1_row(row_label, report.result)
    cells = ", ".join(f"{k}={'-' if v is None else f'{100 * v:.2f}'}" for k, v in report.payload["row"].items()
                      if (k.split("_")[0] in dims and k.split("_")[1] in metrics))
    finish(f"bench K={num_classes} {row_label}: {cells} (mIoU %) -> {out}", dict(report.payload, report=str(out)),
           as_json, details=table)
