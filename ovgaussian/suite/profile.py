"""The benchmark profile (``ovgaussian bench-suite``): Table 1 and the paper's Table 2 with 95 % intervals.

Stages, each reused when its output already exists in ``SuiteConfig.out`` (so an interrupted profile goes on; a
folder made with other settings is refused, see :func:`check_settings`):

1. ``seggaussian synth`` of ScanNet++- and Replica-layout rooms, ``seggaussian build`` of each room's fitted
   3DGS (``SuiteConfig.splats``; ``FitConfig.profile``) and of oracle Gaussians sampled on its mesh (the control
   row), and the train / val / xval split (the ScanNet++-layout rooms train:val, every Replica-layout room xval);
2. one training run per :data:`ovgaussian.suite.config.RUNS` entry, all on the same schedule, ``SuiteConfig.jobs``
   at a time in spawned processes (:func:`run_tasks`);
3. ``ovgaussian bench`` of every Table-1 row and of every ablation run, in the same queue as the trainings: a row
   starts once the runs it scores are done, while other runs may still train; each metric with its 95 %
   percentile bootstrap interval over scenes (``ovgaussian.bench.bootstrap``);
4. ``table1.md``, ``ablation.md``, ``classes.md`` (per-class 3D IoU on the val rooms), the checks of issue #16
   and ``suite.json`` with the CPU and wall time of every stage, this invocation's and every earlier one's
   (``history``).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import resource
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import replace
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from ovgaussian.bench.evaluate import run_bench
from ovgaussian.bench.config import BenchConfig, TABLE1_COLUMNS
from ovgaussian.bench.bootstrap import Interval, bootstrap_ratio, overlaps
from ovgaussian.run.checkpoint import latest_checkpoint
from ovgaussian.metrics import UnseenShare, unseen_share
from ovgaussian.suite.config import ABLATION_ROWS, RUNS, TABLE1_ROWS, RunSpec, SuiteConfig, Table1Row
from ovgaussian.train.loop import train
from ovgaussian.run.config import DataConfig, LossConfig, OptimConfig, TrainConfig, config_to_dict
from seggaussian import shards
from seggaussian.util.atomic import write_json_atomic, write_text_atomic
from seggaussian.util.threads import cap_threads
from seggaussian.pipeline.dataset import build_dataset
from seggaussian.pipeline.config import BuildConfig, SplitConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

#: The metrics the full model must win against both baselines (issue #16: every non-OVA metric).
NON_OVA_COLUMNS = (("3d", "CSA"), ("3d", "CDA"), ("2d", "CSA"), ("2d", "NVA"), ("2d", "CDA"))
#: Columns of the ablation table (the paper's Table 2).
ABLATION_COLUMNS = (("3d", "CSA"), ("2d", "CSA"), ("2d", "NVA"))
#: Least scenes per split the profile must have (issue #16).
MIN_SCENES = {"train": 40, "val": 10, "xval": 8}


class StageTime(NamedTuple):
    """Wall and CPU seconds (this process and its finished children) of one stage."""

    name: str
    wall: float
    cpu: float


class SuiteReport(NamedTuple):
    """What the profile produced.

    Fields:
        out: the profile folder.
        reports: ``{row label: bench JSON payload}`` of Table 1 and ``{run name: payload}`` of the ablation.
        table1, ablation, classes: the markdown tables.
        checks: ``{check: (passed, detail)}``.
        times: one StageTime per stage (stages of one step overlap when ``SuiteConfig.jobs`` > 1).
        wall, cpu: seconds of the whole profile (CPU of this process and its worker processes).
    """

    out: Path
    reports: dict
    table1: str
    ablation: str
    classes: str
    checks: dict
    times: tuple[StageTime, ...]
    wall: float
    cpu: float


def _cpu_seconds() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class Task(NamedTuple):
    """One stage of the profile: ``fn(*args)``, named ``name`` in the log and in ``suite.json``; it starts only
    after the tasks named in ``after`` have finished (a bench row after the runs it scores)."""

    name: str
    fn: Callable
    args: tuple
    after: tuple[str, ...] = ()


def _timed(task: Task, threads: int | None) -> tuple[object, float, float]:
    """(value, wall s, CPU s of this process) of one task; with ``threads``, torch and numba use that many."""
    if threads is not None:
        cap_threads(threads)
    own = resource.getrusage(resource.RUSAGE_SELF)
    t0, c0 = time.perf_counter(), own.ru_utime + own.ru_stime
    value = task.fn(*task.args)
    own = resource.getrusage(resource.RUSAGE_SELF)
    return value, time.perf_counter() - t0, own.ru_utime + own.ru_stime - c0


def run_tasks(tasks: list[Task], jobs: int, say: Callable[[str], None]) -> tuple[list, list[StageTime]]:
    """Values and times of the tasks, in ``tasks`` order. A task's ``after`` names earlier tasks only (ValueError
    otherwise). ``jobs`` > 1: that many spawned processes run them at once, each with ``cpu_count // jobs`` torch
    and numba threads (one training per core costs less CPU than one training on two cores:
    benchmarks/results/bench_suite.md); a task is queued, in list order, once the tasks it comes after are done,
    so a bench row starts while other runs still train. ``jobs`` 1: one after the other here."""
    index = {task.name: i for i, task in enumerate(tasks)}
    for i, task in enumerate(tasks):
        bad = [name for name in task.after if index.get(name, i) >= i]
        if bad:
            raise ValueError(f"task {task.name!r} comes after {bad}: not an earlier task")
    results: list = [None] * len(tasks)
    if jobs <= 1 or len(tasks) <= 1:
        for i, task in enumerate(tasks):
            say(task.name)
            results[i] = _timed(task, None)
    else:
        threads = max(1, (os.cpu_count() or 1) // jobs)
        # spawn: numba's threading layer and torch's threads do not survive fork
        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            waiting, running = list(range(len(tasks))), {}
            while waiting or running:
                for i in [i for i in waiting if all(results[index[n]] is not None for n in tasks[i].after)]:
                    say(f"{tasks[i].name} (queued)")
                    running[pool.submit(_timed, tasks[i], threads)] = i
                    waiting.remove(i)
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in finished:
                    i = running.pop(future)
                    results[i] = future.result()
                    say(f"{tasks[i].name}: done, {results[i][1]:.0f} s wall, {results[i][2]:.0f} s CPU")
    return [r[0] for r in results], [StageTime(t.name, r[1], r[2]) for t, r in zip(tasks, results)]


# --- stages -------------------------------------------------------------------------------------------


class SuiteData(NamedTuple):
    """The profile's datasets of the same rooms and split.

    Fields:
        splats: what the runs train on and the rows are scored on (``SuiteConfig.splats``).
        oracle: Gaussians sampled on the labelled mesh (the control row; the same folder as ``splats`` when the
            profile runs on oracle Gaussians).
    """

    splats: Path
    oracle: Path


def build_data(config: SuiteConfig) -> SuiteData:
    """Synthetic rooms -> the fitted-splat dataset (``SuiteConfig.fit`` per room) and the oracle-Gaussian dataset,
    each with the same split. The rooms are written once; the builds are incremental (content-keyed stage cache),
    so an unchanged dataset costs a fraction of a second."""
    raw = config.out / "raw"
    synth = SynthConfig(width=config.width, num_views=config.views)
    if not (raw / "scannetpp").is_dir():
        synthesize(raw / "scannetpp", config.scenes, config.seed, "scannetpp", synth, jobs=config.jobs)
    if not (raw / "replica").is_dir():
        synthesize(raw / "replica", config.replica_scenes, config.seed, "replica", synth, jobs=config.jobs)
    split = SplitConfig(ratios=(*config.val_ratio, config.replica_scenes), seed=config.seed)
    oracle = config.out / "dataset-oracle" if config.splats == "fit" else config.out / "dataset"
    build_dataset(BuildConfig(
        source="synthetic", root=raw, out=oracle, jobs=config.jobs, gaussians="oracle", seed=config.seed,
        progress=False, oracle=OracleConfig(num_gaussians=config.gaussians), split=split))
    if config.splats == "oracle":
        return SuiteData(oracle, oracle)
    splats = config.out / "dataset"
    build_dataset(BuildConfig(
        source="synthetic", root=raw, out=splats, jobs=config.jobs, gaussians="fit", fit="always",
        fit_config=config.fit, seed=config.seed, progress=False, split=split))
    return SuiteData(splats, oracle)


def split_sizes(dataset: Path) -> dict[str, int]:
    """Scenes per split of a built dataset."""
    return {split: len(shards.list_scenes(dataset, split)) for split in ("train", "val", "xval")}


def run_dir(config: SuiteConfig, name: str) -> Path:
    """The folder of the profile's run ``name``."""
    return config.out / "runs" / name


def train_config(config: SuiteConfig, spec: RunSpec, dataset: Path) -> TrainConfig:
    """The TrainConfig of one run of the profile."""
    return TrainConfig(
        out=run_dir(config, spec.name), epochs=config.epochs, batch_scenes=config.batch_scenes,
        seed=config.seed + spec.seed_offset, model_preset=config.model_preset, use_adapter=spec.use_adapter,
        voxel_size=config.voxel_size, use_coordinates=config.use_coordinates,
        voxel_geometry=config.voxel_geometry, progress=False,
        data=DataConfig(dataset=dataset, num_classes=config.num_classes, pixels_per_view=config.pixels_per_view,
                        holdout_classes=spec.holdout_classes, loss_gaussians=config.loss_gaussians,
                        scene_cache_size=config.scene_cache_size),
        loss=LossConfig(no_3dt_align=spec.no_3dt_align, no_vs_align=spec.no_vs_align,
                        class_balance=config.class_balance, lovasz_weight=config.lovasz_weight,
                        opacity_power=config.opacity_power, unlabelled_as_unseen=spec.unlabelled_as_unseen),
        optim=OptimConfig(lr=config.lr),
    )


def train_run(config: SuiteConfig, spec: RunSpec, dataset: Path) -> Path:
    """Train one run (resumed when interrupted, reused when finished)."""
    run_config = train_config(config, spec, dataset)
    run = run_config.out
    done = run / "suite-done.json"
    if done.is_file() and json.loads(done.read_text()).get("epochs") == config.epochs:
        return run
    train(replace(run_config, resume=latest_checkpoint(run) is not None))
    write_json_atomic(done, {"epochs": config.epochs})
    return run


def bench_config(config: SuiteConfig, dataset: Path, row: Table1Row | None = None, run: Path | None = None,
                 metrics: tuple[str, ...] | None = None) -> BenchConfig:
    """The BenchConfig of a Table-1 row (or of an ablation run with ``run`` and ``metrics``)."""
    fields = dict(dataset=dataset, num_classes=config.num_classes, max_views_per_scene=config.max_views,
                  progress=False)
    if row is not None:
        fields.update(predictor=row.predictor, run=None if row.run is None else run_dir(config, row.run))
        fields.update(dict(row.options))
        if row.stacking_run is not None:
            fields.update(stacking_run=run_dir(config, row.stacking_run))
        if row.ensemble:
            fields.update(ensemble_runs=tuple(run_dir(config, name) for name in row.ensemble))
    if run is not None:
        fields.update(run=run)
    if metrics is not None:
        fields.update(metrics=metrics)
    return BenchConfig(**fields)


def bench_row(config: SuiteConfig, bench: BenchConfig, report_path: Path) -> dict:
    """The bench JSON payload of one row (reused when its report exists)."""
    if report_path.is_file():
        return json.loads(report_path.read_text())
    payload = run_bench(bench).payload
    write_json_atomic(report_path, payload)
    return payload


# --- tables and checks --------------------------------------------------------------------------------


def interval_of(payload: dict, dim: str, metric: str) -> Interval:
    """The metric's value and 95 % interval from a bench payload."""
    m = payload["metrics"].get(dim, {}).get(metric)
    if m is None:
        return Interval(None, None, None, 0, 0)
    ci = m.get("ci95") or [None, None]
    return Interval(m["miou"], ci[0], ci[1], 0, 0)


def _cell(interval: Interval) -> str:
    if interval.value is None:
        return "-"
    if interval.low is None:
        return f"{100 * interval.value:.1f}"
    return f"{100 * interval.value:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def format_table1(reports: dict) -> str:
    """Table 1 (mIoU %, 95 % interval over scenes in brackets)."""
    head = "| method | " + " | ".join(f"{d.upper()} {m}" for d, m in TABLE1_COLUMNS) + " |"
    lines = [head, "|---|" + "---:|" * len(TABLE1_COLUMNS)]
    for label, payload in reports.items():
        lines.append(f"| {label} | " + " | ".join(_cell(interval_of(payload, d, m)) for d, m in TABLE1_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def format_ablation(run_reports: dict, vs_available: bool) -> str:
    """The paper's Table 2 rows at K = 20 on this profile, the paper's values beside them."""
    head = ("| V-S align | 3D-T align | adapter | run | " + " | ".join(f"{d.upper()} {m}" for d, m in ABLATION_COLUMNS)
            + " | paper " + " | paper ".join(f"{d.upper()} {m}" for d, m in ABLATION_COLUMNS) + " |")
    lines = [head, "|---|---|---|---|" + "---:|" * (2 * len(ABLATION_COLUMNS))]
    for row in ABLATION_ROWS:
        vs = "x" if row.vs_align and vs_available else ("(off: no CLIP)" if row.vs_align else "")
        payload = run_reports.get(row.run)
        cells = ["-"] * len(ABLATION_COLUMNS) if payload is None else [
            _cell(interval_of(payload, d, m)) for d, m in ABLATION_COLUMNS]
        lines.append(f"| {vs} | {'x' if row.t3d_align else ''} | {'x' if row.adapter else ''} | {row.run} | "
                     + " | ".join(cells) + " | " + " | ".join(f"{v:.2f}" for v in row.paper) + " |")
    return "\n".join(lines) + "\n"


def format_classes(reports: dict, dim: str = "3d", metric: str = "CSA") -> str:
    """Per-class IoU (%) of every Table-1 row on the metric's set."""
    labels = list(reports)
    first = reports[labels[0]]["metrics"][dim][metric]
    names = list(first["per_class_iou"])
    lines = ["| class | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    for name in names:
        cells = []
        for label in labels:
            v = reports[label]["metrics"][dim][metric]["per_class_iou"].get(name)
            cells.append("-" if v is None else f"{100 * v:.1f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def present_seen_classes(payload: dict, dim: str = "3d") -> list[str]:
    """Seen classes present in the val ground truth (a confusion row with samples)."""
    counts = np.asarray(payload["confusion"][f"val_{dim}"])
    names, unseen = payload["vocabulary"]["names"], set(payload["vocabulary"]["unseen"])
    return [n for i, n in enumerate(names) if counts[i].sum() > 0 and n not in unseen]


def report_unseen_share(payload: dict) -> UnseenShare | None:
    """``ovgaussian.metrics.unseen_share`` of a bench report's NVA confusion matrix; None without NVA."""
    counts = payload["confusion"].get("train_2d")
    if counts is None:
        return None
    names = payload["vocabulary"]["names"]
    return unseen_share(np.asarray(counts), [names.index(n) for n in payload["vocabulary"]["unseen"]])


def nva_unseen_share(payload: dict) -> str:
    """What the unseen classes decide of a report's NVA (:func:`report_unseen_share`), as a sentence."""
    share = report_unseen_share(payload)
    if share is None:
        return "no NVA confusion"
    if share.unseen_right is None or share.seen_only is None:
        return "no class scored"
    ious = payload["metrics"].get("2d", {}).get("NVA", {}).get("per_class_iou", {})
    unseen = ", ".join(f"{n} {'-' if ious.get(n) is None else f'{100 * ious[n]:.1f}'}"
                       for n in payload["vocabulary"]["unseen"])
    return (f"with every unseen pixel right it would be {100 * share.unseen_right:.1f}; "
            f"the seen classes score {100 * share.seen_only:.1f} with the unseen pixels left out; "
            f"unseen classes' IoU: {unseen}")


def checks(reports: dict, full_label: str, baseline_labels: tuple[str, ...], run_reports: dict,
           stacking_labels: tuple[str, ...] = (), method_labels: tuple[str, ...] = ()) -> dict:
    """The model-quality checks of issue #16: ``{name: (passed, detail)}``. ``stacking_labels``: the Table-1
    rows scored with calibrated stacking (OVA > 0 in 3D and 2D, gamma recorded in the report).
    ``method_labels``: the open-vocabulary method rows; NVA >= 60 holds when the full model or one of them reaches
    it, and the detail names each row's NVA and what its unseen classes decide."""
    out = {}
    for label in stacking_labels:
        payload = reports[label]
        gamma = (payload.get("predictor") or {}).get("stacking", {}).get("gamma")
        ova = {dim: interval_of(payload, dim, "OVA") for dim in ("3d", "2d")}
        out[f"OVA > 0 in 3D and 2D with calibrated stacking ({label}), gamma recorded"] = (
            gamma is not None and all(i.value is not None and i.value > 0 for i in ova.values()),
            f"gamma {gamma}; " + "; ".join(f"{d.upper()} OVA {_cell(i)}" for d, i in ova.items()))
    full = reports[full_label]
    for dim, metric in NON_OVA_COLUMNS:
        mine = interval_of(full, dim, metric)
        details, passed = [], mine.value is not None
        for label in baseline_labels:
            other = interval_of(reports[label], dim, metric)
            separate = overlaps(mine, other) is False
            passed = passed and other.value is not None and mine.value > other.value and separate
            details.append(f"{label}: {_cell(other)}")
        out[f"full beats both baselines on {dim.upper()} {metric}, intervals apart"] = (
            bool(passed), f"full {_cell(mine)} vs " + "; ".join(details))
    nva_rows = [full_label] + [label for label in method_labels if label != full_label]
    reaching = [label for label in nva_rows if (interval_of(reports[label], "2d", "NVA").value or 0.0) >= 0.60]
    out["NVA >= 60"] = (bool(reaching),
                        (f"reached by {', '.join(reaching)}" if reaching else "reached by no row") + "; "
                        + "; ".join(f"{label}: NVA {_cell(interval_of(reports[label], '2d', 'NVA'))}, "
                                    + nva_unseen_share(reports[label]) for label in nva_rows))
    for dim in ("3d", "2d"):
        ious = full["metrics"][dim]["CSA"]["per_class_iou"]
        zero = [n for n in present_seen_classes(full, dim) if not (ious.get(n) or 0.0) > 0.0]
        out[f"every seen class of the val rooms above 0 IoU ({dim.upper()})"] = (
            not zero, "zero: " + ", ".join(zero) if zero else f"{len(present_seen_classes(full, dim))} classes > 0")
    order = []
    for dim, metric in ABLATION_COLUMNS:
        values = [interval_of(run_reports[r.run], dim, metric).value if r.run in run_reports else None
                  for r in ABLATION_ROWS]
        if None in values:
            continue
        rising = all(b >= a for a, b in zip(values, values[1:]))
        order.append(f"{dim.upper()} {metric} {'rises' if rising else 'does not rise'} down the rows "
                     f"({', '.join(f'{100 * v:.1f}' for v in values)})")
    if order:
        out["ablation rows order as the paper's"] = (all("does not" not in o for o in order), "; ".join(order))
    return out


#: Issue #27: the full model's 3D CSA on fitted splats is at least this share of what it reaches on oracle Gaussians.
FIT_TO_ORACLE_MIN_SHARE = 0.9


def paired_csa_ratio(fitted: dict, control: dict) -> Interval | None:
    """3D CSA of ``fitted`` over ``control`` (bench payloads) with its paired bootstrap interval over the val rooms
    (``bootstrap_ratio``), or None when the two did not score the same rooms in the same order or hold no per-room
    matrices (a report of an older bench)."""
    rooms = [payload.get("dataset", {}).get("scenes", {}).get("val") for payload in (fitted, control)]
    mats = [payload.get("scene_confusion", {}).get("val_3d") for payload in (fitted, control)]
    if not rooms[0] or rooms[0] != rooms[1] or any(m is None or len(m) != len(rooms[0]) for m in mats):
        return None
    top, bottom = (np.asarray(m, dtype=np.int64) for m in mats)
    return bootstrap_ratio(top, bottom) if top.shape == bottom.shape else None


def control_checks(reports: dict, pairs: Sequence[tuple[str, str]], splats: str, recipe: str | None = None) -> dict:
    """The 90 % check of issue #27: a method on fitted splats against its control (the same method trained and
    scored on the rooms' oracle Gaussians), its 3D CSA on the splats at least ``FIT_TO_ORACLE_MIN_SHARE`` of the
    control's. ``pairs``: ``(fitted, control)`` Table-1 labels; the pair whose fitted row is ``recipe`` (the
    profile's method for fitted splats) decides, else the first (the full model's). The detail gives every pair, each
    ratio with its paired 95 % interval over the val rooms (``paired_csa_ratio``); the rule reads the ratio alone."""
    if splats != "fit" or not pairs:
        return {}

    def share(pair: tuple[str, str]) -> tuple[bool, str]:
        fitted, oracle = (interval_of(reports[label], "3d", "CSA") for label in pair)
        mine, control = fitted.value, oracle.value
        ok = mine is not None and bool(control) and mine >= FIT_TO_ORACLE_MIN_SHARE * control
        ratio = f"{100 * mine / control:.1f} %" if mine is not None and control else "-"
        paired = paired_csa_ratio(reports[pair[0]], reports[pair[1]])
        if paired is not None and paired.low is not None:
            ratio += (f" (paired 95 % interval over the {paired.scenes} val rooms: {100 * paired.low:.1f}-"
                      f"{100 * paired.high:.1f} %)")
        return ok, f"{pair[0]}: fitted {_cell(fitted)} vs oracle {_cell(oracle)}: {ratio}"

    decisive = next((pair for pair in pairs if pair[0] == recipe), pairs[0])
    ok, detail = share(decisive)
    others = [share(pair)[1] for pair in pairs if pair != decisive]
    name = f"3D CSA on fitted splats >= {100 * FIT_TO_ORACLE_MIN_SHARE:.0f} % of the oracle control ({decisive[0]})"
    return {name: (ok, detail + ("; the other methods: " + "; ".join(others) if others else ""))}


def control_pairs(rows: Sequence[Table1Row], trained_on: dict[str, str]) -> list[tuple[str, str]]:
    """``(fitted, control)`` labels: each row trained and scored on oracle Gaussians, with the row of the full
    run on the splats that has the same bench options and as many ensemble members, in the rows' order."""
    pairs = []
    for control in rows:
        if control.scored_on != "oracle" or trained_on.get(control.run) != "oracle":
            continue
        fitted = next((r.label for r in rows if r.run == "full" and r.scored_on == "splats"
                       and r.options == control.options and r.stacking_run is None
                       and len(r.ensemble) == len(control.ensemble)), None)
        if fitted is not None:
            pairs.append((fitted, control.label))
    return pairs


def invocation_history(summary_path: Path) -> list[dict]:
    """The ``times`` and ``total`` of every earlier invocation on this folder, oldest first, from its
    ``suite.json``: a rerun reuses finished stages in seconds, and its own times must not replace the record of
    the run that did the work."""
    try:
        previous = json.loads(summary_path.read_text())
    except (OSError, ValueError):
        return []
    if "history" in previous:
        return list(previous["history"])
    return [{"times": previous["times"], "total": previous["total"]}] if "times" in previous else []


def format_checks(result: dict) -> str:
    return "\n".join(f"- [{'x' if ok else ' '}] {name}: {detail}" for name, (ok, detail) in result.items()) + "\n"


# --- the profile --------------------------------------------------------------------------------------


#: The settings a profile folder was made with (written on its first run, compared on every later one).
SETTINGS_NAME = "suite-settings.json"
#: SuiteConfig fields that change no result: where it is written, the progress display, processes at a time, and
#: whether the ensemble rows are scored too (they add runs and rows, and change none that exist).
SETTINGS_IGNORED = ("out", "progress", "jobs", "ensemble")
#: SuiteConfig fields added after profile folders were first made, with the value every folder made before had.
SETTINGS_ADDED = {"lovasz_weight": 0.0, "voxel_geometry": False, "opacity_power": 0.0}


def check_settings(config: SuiteConfig) -> None:
    """Record ``config`` in a new profile folder; refuse to go on in one made with other settings (its rooms,
    runs and reports are reused by existence, so they would silently belong to the old settings)."""
    path = Path(config.out) / SETTINGS_NAME
    settings = {k: v for k, v in json.loads(json.dumps(config_to_dict(config), default=str)).items()
                if k not in SETTINGS_IGNORED}
    if not path.is_file():
        write_json_atomic(path, settings)
        return
    before = {**SETTINGS_ADDED, **json.loads(path.read_text())}
    changed = [f"{k} {before.get(k)!r} -> {settings.get(k)!r}" for k in sorted(set(before) | set(settings))
               if before.get(k) != settings.get(k)]
    if changed:
        raise ValueError(f"{config.out}: holds a profile made with other settings ({'; '.join(changed)}); "
                         "use a new --out, or the settings recorded in " + SETTINGS_NAME)


def row_runs(row: Table1Row) -> tuple[str, ...]:
    """Names of the runs of :data:`RUNS` a Table-1 row scores: its run, the calibration run of its stacking, and its
    ensemble's other members."""
    return tuple(name for name in (row.run, row.stacking_run, *row.ensemble) if name is not None)


def table1_rows(config: SuiteConfig) -> tuple[Table1Row, ...]:
    """The Table-1 rows of this profile: every row of :data:`TABLE1_ROWS`, less the control rows when the profile
    itself runs on oracle Gaussians (they would repeat the full run's row), and less the ensemble rows without
    ``SuiteConfig.ensemble``."""
    return tuple(r for r in TABLE1_ROWS if (config.splats == "fit" or r.scored_on == "splats")
                 and (config.ensemble or not r.ensemble))


def run_suite(config: SuiteConfig, log: Callable[[str], None] | None = None) -> SuiteReport:
    """Run (or finish) the whole profile; see the module docstring. Library entry point of ``bench-suite``."""
    say = log or (lambda message: None)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    config = replace(config, out=out)
    check_settings(config)
    times: list[StageTime] = []
    started = (time.perf_counter(), _cpu_seconds())
    load_at_start = list(os.getloadavg())

    def stamped(message: str) -> None:
        say(f"[{time.perf_counter() - started[0]:.0f} s] {message}")

    def stage(name: str, fn, *args):
        t0, c0 = time.perf_counter(), _cpu_seconds()
        stamped(name)
        value = fn(*args)
        times.append(StageTime(name, time.perf_counter() - t0, _cpu_seconds() - c0))
        return value

    data = stage("data: synth + fit + build + split", build_data, config)
    dataset = data.splats
    sizes = split_sizes(dataset)
    rows = table1_rows(config)
    needed = {name for row in rows for name in row_runs(row)}
    if config.ablation:
        needed |= {row.run for row in ABLATION_ROWS}
    specs = [spec for spec in RUNS if spec.name in needed]
    runs = {spec.name: run_dir(config, spec.name) for spec in specs}
    # one queue: the trainings first (longest first), then each bench row as soon as the runs it scores are done
    tasks = [Task(f"train: {spec.name}", train_run,
                  (config, spec, data.oracle if spec.trained_on == "oracle" else dataset)) for spec in specs]
    reports_dir = out / "reports"
    tasks += [Task(f"bench: {row.label}", bench_row,
                   (config, bench_config(config, data.oracle if row.scored_on == "oracle" else dataset, row),
                    reports_dir / f"table1-{index:02d}.json"),
                   tuple(f"train: {name}" for name in row_runs(row)))
              for index, row in enumerate(rows)]
    # a run scored by a Table-1 row without an open-vocabulary method needs no bench of its own for Table 2
    plain_rows = {r.run: r.label for r in rows if r.run is not None and not r.options and not r.stacking_run
                  and not r.ensemble and r.scored_on == "splats"}
    ablation_runs = sorted({row.run for row in ABLATION_ROWS}) if config.ablation else []
    ablation_only = [name for name in ablation_runs if name not in plain_rows]
    tasks += [Task(f"bench: ablation {name}", bench_row,
                   (config, bench_config(config, dataset, run=runs[name], metrics=("CSA", "NVA")),
                    reports_dir / f"ablation-{name}.json"), (f"train: {name}",))
              for name in ablation_only]
    values, task_times = run_tasks(tasks, config.jobs, stamped)
    times += task_times
    values = values[len(specs):]  # the trainings' values are their run folders, known beforehand
    reports = {row.label: payload for row, payload in zip(rows, values)}
    extra = dict(zip(ablation_only, values[len(rows):]))
    run_reports = {name: reports[plain_rows[name]] if name in plain_rows else extra[name] for name in ablation_runs}

    full_label = plain_rows["full"]
    baselines = tuple(r.label for r in rows if r.predictor != "model")
    table1 = format_table1(reports)
    ablation = format_ablation(run_reports, vs_available=False) if config.ablation else ""
    classes = format_classes(reports)
    result = {"profile size (at least 40 train, 10 val, 8 xval rooms)": (
        all(sizes[k] >= n for k, n in MIN_SCENES.items()), ", ".join(f"{sizes[k]} {k}" for k in MIN_SCENES)),
        **checks(reports, full_label, baselines, run_reports,
                 tuple(r.label for r in rows if r.stacking_run is not None),
                 tuple(r.label for r in rows if r.predictor == "model" and r.label != full_label
                       and r.scored_on == "splats")),
        **control_checks(reports, control_pairs(rows, {s.name: s.trained_on for s in RUNS if s.name in runs}),
                         config.splats, next((r.label for r in rows if r.fit_recipe), None))}
    wall, cpu = time.perf_counter() - started[0], _cpu_seconds() - started[1]
    invocation = {"times": [t._asdict() for t in times],
                  "total": {"wall_s": wall, "cpu_s": cpu, "load_average_start": load_at_start,
                            "load_average_end": list(os.getloadavg()), "cores": os.cpu_count(),
                            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}}
    summary = {
        "config": config_to_dict(config),
        "splits": sizes,
        "runs": {name: config_to_dict(train_config(config, spec, data.oracle if spec.trained_on == "oracle" else dataset))
                 for spec in RUNS for name in [spec.name] if name in runs},
        "table1": {label: {f"{d}_{m}": list(interval_of(p, d, m)[:3]) for d, m in TABLE1_COLUMNS}
                   for label, p in reports.items()},
        "ablation": {name: {f"{d}_{m}": list(interval_of(p, d, m)[:3]) for d, m in ABLATION_COLUMNS}
                     for name, p in run_reports.items()},
        "checks": {name: {"passed": ok, "detail": detail} for name, (ok, detail) in result.items()},
        **invocation,
        "history": invocation_history(out / "suite.json") + [invocation],
    }
    write_json_atomic(out / "suite.json", summary)
    write_text_atomic(out / "table1.md", table1)
    write_text_atomic(out / "ablation.md", ablation)
    write_text_atomic(out / "classes.md", classes)
    write_text_atomic(out / "checks.md", format_checks(result))
    return SuiteReport(out, {**reports, **{f"ablation {k}": v for k, v in run_reports.items()}}, table1, ablation,
                       classes, result, tuple(times), wall, cpu)
