"""Reports of the stage sweeps: Markdown tables (fastest first, Pareto rows and the shipped default marked),
the default's verdict, the per-scene table of build rows, and a matplotlib plot (optional dependency).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from seggaussian.util.atomic import atomic_path, write_text_atomic
from seggaussian.tools.sweep.pareto import (PARETO_TIME_TOLERANCE, QUALITY, QUALITY_TOLERANCE, StageSweepResult, Trial,
                                      dominators)


# --- output ---------------------------------------------------------------------------------------------
def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not np.isfinite(value):
            return "nan"
        return f"{value:.4g}"
    return str(value)


#: Extra columns of each stage's table (metric keys).
TABLE_METRICS = {
    "fit": ("novel_ssim", "novel_l1", "iterations_run", "gaussians"),
    "transfer": ("label_accuracy", "unlabelled_kept", "ignored_share", "wrong_label_share", "spacing_median",
                 "gate_median", "label_points"),
    "render": ("labelled_agreement", "unlabelled_kept", "ignored_share", "feature_residual_mean", "feature_residual_max",
               "residual_alpha_mean", "image_size"),
    "build": ("scenes_per_minute", "stages_run", "stages_cached", "shards_rewritten"),
}


def seconds_label(stage: str) -> str:
    """What the seconds of a row are: per scene for builds, summed over the scenes for the other stages."""
    return "seconds per scene" if stage == "build" else "seconds (all scenes)"


def format_table(result: StageSweepResult) -> str:
    """Markdown table of the rows, fastest first; ``P`` marks Pareto-optimal rows, ``D`` the shipped default."""
    if not result.trials:
        return f"(no {result.stage} rows)"
    knobs = list(result.trials[0].settings)
    extra = TABLE_METRICS[result.stage]
    header = ["mark", "varied", *knobs, seconds_label(result.stage), result.quality_name, *extra]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for t in sorted(result.trials, key=lambda t: (t.seconds, -t.quality if np.isfinite(t.quality) else 0)):
        mark = ("P" if t.pareto else "") + ("D" if t.is_default else "")
        cells = [mark or ".", t.knob, *[_fmt(t.settings.get(k)) for k in knobs], f"{t.seconds:.3f}", _fmt(t.quality),
                 *[_fmt(t.metrics.get(k)) for k in extra]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _row_label(t: Trial) -> str:
    """``knob=value`` of a row (``a=1, b=2`` for a row varying several knobs; ``base`` for the base)."""
    if t.knob == "base":
        return "base"
    return ", ".join(f"{k}={_fmt(t.settings.get(k))}" for k in t.knob.split("+"))


def default_verdict(result: StageSweepResult) -> str:
    """One sentence: is the shipped default on the Pareto front?"""
    defaults = result.default_trials
    if not defaults:
        return f"{result.stage}: the shipped default was not among the rows (quick/base overrides)"
    parts = []
    for d in defaults:
        if d.pareto:
            parts.append(f"{result.stage}: shipped default is Pareto-optimal "
                         f"({result.quality_name} {_fmt(d.quality)} in {d.seconds:.3f} s)")
        else:
            seconds = np.array([t.seconds for t in result.trials], np.float64)
            quality = np.array([t.quality for t in result.trials], np.float64)
            rows = dominators(seconds, quality, result.trials.index(d), PARETO_TIME_TOLERANCE,
                              QUALITY_TOLERANCE[result.stage])
            better = [t for t, r in zip(result.trials, rows) if r and np.isfinite(t.quality)]
            alt = min(better, key=lambda t: t.seconds) if better else None
            parts.append(f"{result.stage}: shipped default is NOT on the Pareto front ({result.quality_name} "
                         f"{_fmt(d.quality)} in {d.seconds:.3f} s)"
                         + (f"; dominated by {_row_label(alt)} ({_fmt(alt.quality)} in {alt.seconds:.3f} s)"
                            if alt else ""))
    return "; ".join(parts)


def plot_trials(results: Sequence[StageSweepResult], path: Path) -> Path:
    """A PNG with one panel per stage: seconds (log) against quality, the Pareto front joined, the shipped
    default circled. Needs matplotlib (optional): ImportError with the install command otherwise."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("--plot needs matplotlib: pip install matplotlib") from None
    path = Path(path)
    ncols = min(3, max(1, len(results)))
    nrows = -(-len(results) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.5 * ncols, 4.2 * nrows), squeeze=False)
    for ax in axes.flat[len(results):]:
        ax.set_visible(False)
    for ax, result in zip(axes.flat, results):
        xs = np.array([t.seconds for t in result.trials])
        ys = np.array([t.quality for t in result.trials])
        ax.scatter(xs, ys, c=["tab:red" if t.pareto else "tab:gray" for t in result.trials], s=24, zorder=2)
        front = sorted((t for t in result.trials if t.pareto), key=lambda t: t.seconds)
        if front:
            ax.step([t.seconds for t in front], [t.quality for t in front], where="post", c="tab:red", lw=1, zorder=1)
        for t in result.trials:
            label = _row_label(t)
            ax.annotate(label, (t.seconds, t.quality), fontsize=6, xytext=(3, 3), textcoords="offset points")
            if t.is_default:
                ax.scatter([t.seconds], [t.quality], s=140, facecolors="none", edgecolors="tab:blue", lw=1.5,
                           zorder=3, label="shipped default")
        if np.all(xs > 0):
            ax.set_xscale("log")
        ax.set_xlabel(seconds_label(result.stage))
        ax.set_ylabel(f"{result.quality_name} ({QUALITY[result.stage][1]})")
        ax.set_title(f"{result.stage} ({len(result.scenes)} scene{'s' if len(result.scenes) != 1 else ''})")
        ax.grid(alpha=0.3)
        if any(t.is_default for t in result.trials):
            ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    try:
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=120, format="png")
    finally:
        plt.close(fig)
    return path


def format_build_scenes(result: StageSweepResult) -> str:
    """Per-scene table of every build row: what ran, what was cached, views stored, Gaussians left unlabelled."""
    header = ["executor", "jobs", "cache", "scene", "status", "stages run", "stages cached", "views stored",
              "gaussians", "ignored (outside box / beyond gate)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for t in result.trials:
        for p in t.metrics.get("per_scene", []):
            lines.append("| " + " | ".join([
                t.settings["executor"], str(t.settings["jobs"]), t.settings["cache"], p["scene"], p["status"],
                ",".join(p["stages_run"]) or "-", ",".join(p["stages_cached"]) or "-", _fmt(p.get("views_stored")),
                _fmt(p.get("gaussians")),
                f"{_fmt(p.get('gaussians_ignored'))} ({_fmt(p.get('gaussians_outside_box'))} / "
                f"{_fmt(p.get('gaussians_beyond_gate'))})"]) + " |")
    return "\n".join(lines)


def write_markdown(results: Sequence[StageSweepResult], path: Path, command_line: str) -> Path:
    """The tables of ``results`` with the command that produced them and the default verdicts (atomic write)."""
    path = Path(path)
    lines = ["# Stage sweeps: time against error", "",
             f"Produced by `{command_line}`.", "",
             "`P` = Pareto-optimal (no other row is at least as fast and at least as good), `D` = shipped default. "
             "Rows vary one knob from the base (`varied`); seconds are summed over the scenes.", ""]
    for r in results:
        m = r.machine
        lines += [f"## {r.stage}: {r.quality_name} ({QUALITY[r.stage][1]}) vs seconds", "",
                  f"{len(r.scenes)} scenes: {', '.join(r.scenes)}. Machine: {m.get('cpus')} CPUs, load average "
                  f"{_fmt(m.get('load_average_1min'))}" + (" -- **measured under load**" if m.get("under_load") else ""),
                  ""]
        if r.config.get("command"):
            lines += [f"Measured by `{r.config['command']}`.", ""]
        lines += [format_table(r), "", default_verdict(r), ""]
        if r.stage == "build":
            lines += [format_build_scenes(r), ""]
        lines += [f"- skipped: {s}" for s in r.skipped]
        if r.skipped:
            lines.append("")
    write_text_atomic(path, "\n".join(lines))
    return path
