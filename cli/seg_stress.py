"""``seggaussian stress``: the numerical-stability suite, runnable on any installation."""

from __future__ import annotations

import sys

import click

from cli._output import finish, guarded, json_option


@click.command("stress")
@click.option("--cases", default=20, show_default=True, help="Cases generated per family.")
@click.option("--seed", default=0, show_default=True, help="Seed of the case generators.")
@click.option("--backend", type=click.Choice(["auto", "fast", "reference"]), default="auto", show_default=True,
              help="Rasterizer backend exercised.")
@json_option
@guarded
def command(cases: int, seed: int, backend: str, as_json: bool) -> None:
    """Malformed and extreme PLYs, degenerate cameras, label-transfer ties, extreme losses: counts clean
    errors, repairs and NaN/Inf outputs (which must be 0). Exit status 1 when anything failed."""
    from tqdm import tqdm

    from ovgaussian.train.stress_losses import LOSS_FAMILY
    from seggaussian.tools.stress import DATASET_FAMILIES, StressConfig, run_stress

    config = StressConfig(cases=cases, seed=seed, backend=backend)
    families = (*DATASET_FAMILIES, LOSS_FAMILY)  # the dataset package's cases, then the model package's
    with tqdm(total=cases * len(families), desc="stress", disable=as_json, file=sys.stderr) as bar:
        report = run_stress(config, progress=lambda r: bar.update(1), families=families)
    lines = [f"{family:12s} " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
             for family, counts in report.by_family.items()]
    lines += [f"FAILED {c.family} {c.name}: {c.outcome}: {c.detail}" for c in report.failures]
    summary = (f"stress: {report.cases_tried} cases, {report.clean_errors} clean errors, {report.repairs} repairs, "
               f"{report.nan_inf_found} NaN/Inf outputs, {report.crashes} crashes -> "
               f"{'PASS' if report.passed else 'FAIL'}")
    finish(summary, {"config": config.__dict__, **report.to_dict()}, as_json, "\n".join(lines))
    if not report.passed:
        raise SystemExit(1)
