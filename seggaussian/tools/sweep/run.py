"""Stage sweeps (CLI ``seggaussian bench --stage fit|transfer|render|build``): each stage's speed knobs swept one
at a time around its shipped default, every row timed and scored against ground truth from the labelled mesh
(or held-out views), the Pareto front of seconds against quality marked.

Data flow: ``sweep_data.prepare_data`` (the default synthetic set, synthesized once into the work folder, or a
raw tree) -> ``sweep_data.discover_scenes`` -> one stage's sweep (``sweep_fit``, ``sweep_transfer``,
``sweep_render``, ``sweep_build``; their module docstrings say what ground truth each uses) -> ``Trial`` rows ->
``pareto.mark_pareto`` -> ``StageSweepResult`` -> ``sweep_report`` (Markdown tables, verdicts, PNG plot) or JSON.

"Stage sweep" is this tool's name in the code; the CLI keeps the command name ``bench`` that users know.
"""

from __future__ import annotations

from seggaussian.tools.sweep.pareto import PARETO_TIME_TOLERANCE, QUALITY, QUALITY_TOLERANCE, StageSweepResult, mark_pareto
from seggaussian.tools.sweep.build import sweep_build
from seggaussian.tools.sweep.config import STAGES, StageSweepConfig
from seggaussian.tools.sweep.data import Progress, discover_scenes, machine_info, prepare_data
from seggaussian.tools.sweep.fit import sweep_fit
from seggaussian.tools.sweep.render import sweep_render
from seggaussian.tools.sweep.transfer import sweep_transfer


def run_stage_sweep(config: StageSweepConfig, progress: Progress | None = None) -> StageSweepResult:
    """Sweep one stage on the configured data; see the module docstring."""
    machine = machine_info()
    root = prepare_data(config, progress)
    tasks = discover_scenes(root, config)
    if config.stage == "fit":
        trials, skipped = sweep_fit(config, tasks, progress)
    elif config.stage == "transfer":
        trials, skipped = sweep_transfer(config, tasks, progress)
    elif config.stage == "render":
        trials, skipped = sweep_render(config, tasks, progress)
    elif config.stage == "build":
        trials, skipped = sweep_build(config, tasks, root, progress)
    else:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {config.stage!r}")
    trials = mark_pareto(trials, PARETO_TIME_TOLERANCE, QUALITY_TOLERANCE[config.stage])
    return StageSweepResult(config.stage, QUALITY[config.stage][0], trials,
                            [t.scene_id for t in tasks], skipped, machine, config.to_dict())
