"""``ovgaussian bench-suite``: the benchmark profile (Table 1 + the paper's Table 2, 95 % intervals over scenes)."""

from __future__ import annotations

from pathlib import Path

import click

from cli._config_options import config_option
from cli._output import finish, guarded, json_option
from ovgaussian.suite.config import SuiteConfig

D = SuiteConfig()


@click.command("bench-suite")
@config_option(SuiteConfig, "out", "--out", type=click.Path(path_type=Path, file_okay=False), default=D.out,
               show_default=True)
@config_option(SuiteConfig, "scenes", "--scenes", type=click.IntRange(min=1), default=D.scenes, show_default=True)
@config_option(SuiteConfig, "replica_scenes", "--replica-scenes", type=click.IntRange(min=1), default=D.replica_scenes,
               show_default=True)
@config_option(SuiteConfig, "splats", "--splats", type=click.Choice(["fit", "oracle"]), default=D.splats,
               show_default=True)
@config_option(SuiteConfig, "gaussians", "--gaussians", type=click.IntRange(min=1), default=D.gaussians,
               show_default=True)
@config_option(SuiteConfig, "epochs", "--epochs", type=click.IntRange(min=1), default=D.epochs, show_default=True)
@config_option(SuiteConfig, "lovasz_weight", "--lovasz-weight", type=click.FloatRange(min=0), default=D.lovasz_weight,
               show_default=True)
@config_option(SuiteConfig, "voxel_geometry", "--voxel-geometry/--no-voxel-geometry", default=D.voxel_geometry,
               show_default=True)
@config_option(SuiteConfig, "opacity_power", "--opacity-power", type=click.FloatRange(min=0), default=D.opacity_power,
               show_default=True)
@config_option(SuiteConfig, "loss_gaussians", "--loss-gaussians", type=click.IntRange(min=0), default=D.loss_gaussians or 0,
               show_default=True)
@config_option(SuiteConfig, "max_views", "--max-views", type=click.IntRange(min=1), default=D.max_views,
               show_default=True)
@config_option(SuiteConfig, "ablation", "--ablation/--no-ablation", default=D.ablation, show_default=True)
@config_option(SuiteConfig, "ensemble", "--ensemble/--no-ensemble", default=D.ensemble, show_default=True)
@config_option(SuiteConfig, "zoo", "--zoo/--no-zoo", default=D.zoo, show_default=True)
@config_option(SuiteConfig, "zoo_fit_iterations", "--zoo-fit-iterations", type=click.IntRange(min=1),
               default=D.zoo_fit_iterations, show_default=True)
@config_option(SuiteConfig, "jobs", "--jobs", type=click.IntRange(min=1), default=D.jobs, show_default=True)
@config_option(SuiteConfig, "seed", "--seed", type=int, default=D.seed, show_default=True)
@config_option(SuiteConfig, "progress", "--progress/--no-progress", default=D.progress, show_default=True)
@json_option
@guarded
def command(out, scenes, replica_scenes, splats, gaussians, epochs, lovasz_weight, voxel_geometry, opacity_power,
            loss_gaussians, max_views, ablation, ensemble, zoo, zoo_fit_iterations, jobs, seed, progress, as_json):
    """Run the benchmark profile into OUT (finished stages found there are reused)."""
    from ovgaussian.suite.profile import run_suite

    config = SuiteConfig(out=out, scenes=scenes, replica_scenes=replica_scenes, splats=splats, gaussians=gaussians,
                         epochs=epochs, lovasz_weight=lovasz_weight, voxel_geometry=voxel_geometry,
                         opacity_power=opacity_power, loss_gaussians=loss_gaussians or None,
                         max_views=max_views, ablation=ablation, ensemble=ensemble, zoo=zoo,
                         zoo_fit_iterations=zoo_fit_iterations, jobs=jobs, seed=seed,
                         progress=progress)
    report = run_suite(config, log=(lambda m: click.echo(m, err=True)) if progress and not as_json else None)
    passed = sum(ok for ok, _ in report.checks.values())
    wall, cpu = report.wall, report.cpu
    finish(f"bench-suite: {len(report.reports)} reports, checks {passed}/{len(report.checks)} passed, "
           f"{wall:.0f} s wall, {cpu:.0f} s CPU -> {report.out}",
           {"out": str(report.out), "checks": {k: {"passed": ok, "detail": d} for k, (ok, d) in report.checks.items()},
            "times": [t._asdict() for t in report.times], "wall_s": wall, "cpu_s": cpu}, as_json,
           details=report.table1 + "\n" + report.ablation + "\n" + report.zoo + "\n" + "".join(
               f"- [{'x' if ok else ' '}] {k}: {d}\n" for k, (ok, d) in report.checks.items()))
