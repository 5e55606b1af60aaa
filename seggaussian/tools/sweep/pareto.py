"""The Pareto harness of the stage sweeps: measured rows (``Trial``), a stage's result, the one-knob-at-a-time
row plan and the Pareto front (minimize seconds, maximize the stage's quality).

Nothing here knows a stage's code: the per-stage sweeps (``sweep_fit``, ``sweep_transfer``, ``sweep_render``,
``sweep_build``) produce ``Trial`` rows, ``stage_sweep.run_stage_sweep`` marks the front with ``mark_pareto``.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

#: Quality axis of each stage (higher is better) and its unit, as printed in tables and plots.
QUALITY = {
    "fit": ("novel_psnr", "dB"),
    "transfer": ("label_agreement", "share"),
    "render": ("pixel_agreement", "share"),
    "build": ("identical_output", "0/1"),
}
#: Relative timing differences below this count as noise when marking the Pareto front of measured rows
#: (run-to-run noise on these VMs is 15-30% on medians, see shared/notes/cpu-kernels.md; 0.15 keeps a
#: setting whose only change is a threshold from "beating" an identical-cost row by noise alone).
PARETO_TIME_TOLERANCE = 0.15
#: Quality differences at most this large count as ties when marking the Pareto front: 0.1 percentage point
#: of accuracy / pixel agreement (below what one scene's sampling changes), 0.05 dB of PSNR (the fit's own
#: ``min_psnr_gain``); builds are 0/1.
QUALITY_TOLERANCE = {"fit": 0.05, "transfer": 1e-3, "render": 1e-3, "build": 0.0}


class Trial(NamedTuple):
    """One measured setting of a stage.

    Fields:
        stage: ``fit``, ``transfer``, ``render`` or ``build``.
        knob: the knob this row varies from the base (``base`` for the base row).
        settings: value of every swept knob in this row.
        seconds: time of the stage summed over the swept scenes (median over repeats); build rows: wall
            time of the whole build divided by the number of scenes.
        quality: the stage's quality (``QUALITY[stage]``; higher is better); NaN when not measurable.
        metrics: stage-specific errors and counts (JSON-ready).
        is_default: the row is the shipped default setting of the stage.
        pareto: no other row is at least as fast and at least as good, and strictly better in one.
    """

    stage: str
    knob: str
    settings: dict
    seconds: float
    quality: float
    metrics: dict
    is_default: bool
    pareto: bool = False


class StageSweepResult(NamedTuple):
    """All rows of one stage's sweep.

    Fields:
        stage: the swept stage.
        quality_name: name of the quality axis (``QUALITY[stage][0]``).
        trials: the rows, Pareto flags set.
        scenes: scene ids the rows were measured on.
        skipped: settings that could not run, with the reason (e.g. Ray not installed).
        machine: CPU count and load average when the sweep started (timings under load are marked).
        config: the ``StageSweepConfig`` as a dict.
    """

    stage: str
    quality_name: str
    trials: list
    scenes: list
    skipped: list
    machine: dict
    config: dict

    def to_dict(self) -> dict:
        out = self._asdict()
        out["trials"] = [t._asdict() for t in self.trials]
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "StageSweepResult":
        trials = [Trial(**{**t, "quality": float("nan") if t["quality"] is None else t["quality"]})
                  for t in d["trials"]]
        return cls(d["stage"], d["quality_name"], trials, list(d["scenes"]), list(d["skipped"]), dict(d["machine"]),
                   dict(d["config"]))

    @property
    def default_trials(self) -> list:
        return [t for t in self.trials if t.is_default]


# --- Pareto front -------------------------------------------------------------------------------------
def mark_pareto(trials: Sequence[Trial], time_tolerance: float = 0.0, quality_tolerance: float = 0.0) -> list[Trial]:
    """Rows with ``pareto`` set: not dominated in (seconds down, quality up). NaN quality is never optimal."""
    seconds = np.array([t.seconds for t in trials], np.float64)
    quality = np.array([t.quality for t in trials], np.float64)
    flags = pareto_mask(seconds, quality, time_tolerance, quality_tolerance)
    return [t._replace(pareto=bool(f)) for t, f in zip(trials, flags)]


def pareto_mask(seconds: np.ndarray, quality: np.ndarray, time_tolerance: float = 0.0,
                quality_tolerance: float = 0.0) -> np.ndarray:
    """``[T]`` bool: row i is optimal when no row j dominates it. With ``time_tolerance`` = 0, j dominates i
    when seconds_j <= seconds_i and quality_j >= quality_i with one of the two strict. With a tolerance t,
    times within a factor (1 +- t) count as equal (timing noise): j dominates i when quality_j >= quality_i
    and either seconds_j < (1 - t) seconds_i, or seconds_j <= (1 + t) seconds_i and quality_j > quality_i.
    With ``quality_tolerance`` q, qualities within q count as equal (j needs quality_j >= quality_i - q, and
    quality_j > quality_i + q to beat a row of equal time). Rows with a NaN are not optimal and dominate nothing."""
    seconds, quality = np.asarray(seconds, np.float64), np.asarray(quality, np.float64)
    ok = np.isfinite(seconds) & np.isfinite(quality)
    out = np.zeros(len(seconds), bool)
    for i in np.flatnonzero(ok):
        out[i] = not (ok & dominators(seconds, quality, i, time_tolerance, quality_tolerance)).any()
    return out


def dominators(seconds: np.ndarray, quality: np.ndarray, i: int, time_tolerance: float = 0.0,
               quality_tolerance: float = 0.0) -> np.ndarray:
    """``[T]`` bool: the rows that dominate row ``i`` (the rule of ``pareto_mask``)."""
    t, q = float(time_tolerance), float(quality_tolerance)
    if t == 0.0:
        faster, not_slower = seconds < seconds[i], seconds <= seconds[i]
    else:
        faster, not_slower = seconds < (1.0 - t) * seconds[i], seconds <= (1.0 + t) * seconds[i]
    return (quality >= quality[i] - q) & (faster | (not_slower & (quality > quality[i] + q)))


# --- row plan -------------------------------------------------------------------------------------------
def one_at_a_time(base: dict, grids: dict) -> list[tuple[str, dict]]:
    """(knob, settings) rows: the base, then each other value of each knob with the rest at base."""
    rows = [("base", dict(base))]
    for knob, values in grids.items():
        for value in values:
            if value != base[knob]:
                rows.append((knob, {**base, knob: value}))
    return rows
