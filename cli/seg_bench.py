"""``seggaussian bench``: the stage sweeps (``seggaussian.tools.sweep.run``): sweep a stage's speed knobs and
measure time against error (Pareto front). The command keeps the name ``bench`` that users know; in the code
the tool is the "stage sweep" (``ovgaussian bench`` is the model evaluation)."""

from __future__ import annotations

import shlex
import sys
from dataclasses import replace
from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from seggaussian.tools.sweep.config import STAGES, StageSweepConfig, quick_config, with_params

STAGE_CHOICES = ("fit", "transfer", "render", "build", "all")


@click.command("bench")
@click.option("--stage", "stages", multiple=True, type=click.Choice(STAGE_CHOICES),
              help="Stage to sweep (repeat for several; all = every stage).")
@config_option(StageSweepConfig, "data", "--data", type=click.Path(path_type=Path), default=None)
@config_option(StageSweepConfig, "work_dir", "--work-dir", type=click.Path(path_type=Path),
               default=StageSweepConfig.work_dir, show_default=True)
@click.option("--scenes", type=int, default=None, help="Use at most this many scenes (default: all; quick: 1).")
@config_option(StageSweepConfig, "seed", "--seed", type=int, default=0, show_default=True)
@click.option("--quick", is_flag=True, help="Tiny sweep on one tiny synthetic scene (seconds).")
@click.option("--plot", type=click.Path(path_type=Path), default=None, help="Write a PNG plot (needs matplotlib).")
@click.option("--markdown", type=click.Path(path_type=Path), default=None,
              help="Write the tables (with the command line) to this Markdown file.")
@click.option("--param", "params", multiple=True,
              help="Override a sweep field of the stage: NAME=V1,V2 (e.g. iterations=300,1000; views=2).")
@click.option("--base", "base", multiple=True,
              help="Override the base row: NAME=VALUE (fit: a FitConfig field; transfer: a swept knob).")
@click.option("--from-json", "from_json", multiple=True, type=click.Path(path_type=Path),
              help="Load results saved with --json instead of running (repeat; combine with --markdown/--plot).")
@json_option
@guarded
def command(stages, data, work_dir, scenes, seed, quick, plot, markdown, params, base, from_json, as_json) -> None:
    """Stage sweeps: time against error for each setting of a stage's speed knobs, with ground truth from the
    synthetic meshes (or held-out views / meshes of real raw data). P marks Pareto-optimal rows, D the shipped
    default. (The command is named bench for continuity; it benchmarks pipeline stages, not the model: that is
    ovgaussian bench.)"""
    from seggaussian.tools.sweep.pareto import PARETO_TIME_TOLERANCE, QUALITY_TOLERANCE, StageSweepResult, mark_pareto
    from seggaussian.tools.sweep.run import run_stage_sweep
    from seggaussian.tools.sweep.report import default_verdict, format_table, plot_trials, write_markdown

    if not stages and not from_json:
        raise click.UsageError("give --stage (fit, transfer, render, build or all) or --from-json")
    wanted = [s for s in STAGES if s in stages or "all" in stages]
    results = []
    for path in from_json:
        import json

        try:
            payload = json.loads(Path(path).read_text())
            loaded = [StageSweepResult.from_dict(r) for r in payload["results"]]
        except (ValueError, KeyError, TypeError) as exc:
            raise click.ClickException(f"{path}: not a `seggaussian bench --json` output ({exc})") from None
        # the Pareto flags are recomputed with the current rule (tolerances) when tables are re-rendered
        results += [r._replace(trials=mark_pareto(r.trials, PARETO_TIME_TOLERANCE, QUALITY_TOLERANCE[r.stage]))
                    for r in loaded]
    for stage in wanted:
        config = quick_config(stage) if quick else StageSweepConfig(stage=stage)
        config = replace(config, data=data, work_dir=work_dir, seed=seed,
                         scenes=config.scenes if scenes is None else scenes)
        try:
            config = with_params(config, params, base)
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from None

        def say(message: str) -> None:  # stderr: never mixed into the JSON document on stdout
            click.echo(f"[bench] {message}", err=True)

        results.append(run_stage_sweep(config, progress=say))
    if plot is not None:
        plot_trials(results, plot)
    args = sys.argv[sys.argv.index("bench") + 1:] if "bench" in sys.argv else []
    command_line = shlex.join(["seggaussian", "bench", *args])
    if not from_json:
        results = [r._replace(config={**r.config, "command": command_line}) for r in results]
    if markdown is not None:
        write_markdown(results, markdown, command_line)
    details = "\n\n".join(f"## {r.stage} ({len(r.scenes)} scenes)\n{format_table(r)}\n{default_verdict(r)}"
                          + "".join(f"\nskipped: {s}" for s in r.skipped) for r in results)
    on_front = sum(1 for r in results for d in r.default_trials if d.pareto)
    defaults = sum(len(r.default_trials) for r in results)
    loaded = any(r.machine.get("under_load") for r in results)
    summary = (f"bench {','.join(r.stage for r in results)}: {sum(len(r.trials) for r in results)} rows, "
               f"{sum(t.pareto for r in results for t in r.trials)} Pareto-optimal; shipped defaults on the front: "
               f"{on_front}/{defaults}" + (" (measured under load)" if loaded else "")
               + (f"; plot {plot}" if plot else ""))
    finish(summary, {"results": [r.to_dict() for r in results], "verdicts": [default_verdict(r) for r in results]},
           as_json, details)
