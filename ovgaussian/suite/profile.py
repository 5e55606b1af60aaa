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
4. ``table1.md``, ``ablation.md``, ``classes.md`` (per-class 3D IoU on the val rooms) and the checks of issues #16
   and #27 (``ovgaussian.suite.report``); with ``SuiteConfig.zoo``, ``zoo.md``, ``zoo.json`` and the checks of the
   splat zoo of issue #54 (``ovgaussian.suite.zoo``: its renditions are built and its runs trained in the same
   queue); ``suite.json`` with the CPU and wall time of every stage, this invocation's and every earlier one's
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

from ovgaussian.bench.evaluate import dataset_fingerprint, run_bench
from ovgaussian.bench.config import BenchConfig, TABLE1_COLUMNS
from ovgaussian.run.checkpoint import CONFIG_NAME, latest_checkpoint, weights_sha256
from ovgaussian.run.folder import changed_settings
from ovgaussian.suite.config import (ABLATION_ROWS, RUNS, TABLE1_ROWS, ZOO_RENDITIONS, ZOO_RUNS, RunSpec, SuiteConfig,
                                     Table1Row)
from ovgaussian.suite import zoo as Z
from ovgaussian.suite.report import (ABLATION_COLUMNS, checks, control_checks, control_pairs, format_ablation,
                                     format_checks, format_classes, format_table1, interval_of)
from ovgaussian.train.loop import train
from ovgaussian.run.config import DataConfig, LossConfig, OptimConfig, TrainConfig, config_to_dict
from seggaussian import shards
from seggaussian.util.atomic import write_json_atomic, write_text_atomic
from seggaussian.util.threads import cap_threads
from seggaussian.util.workers import pool_options
from seggaussian.pipeline.dataset import build_dataset
from seggaussian.pipeline.config import BuildConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

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
        zoo: the splat zoo's tables (empty without ``SuiteConfig.zoo``).
        checks: ``{check: (passed, detail)}``.
        times: one StageTime per stage (stages of one step overlap when ``SuiteConfig.jobs`` > 1).
        wall, cpu: seconds of the whole profile (CPU of this process and its worker processes).
    """

    out: Path
    reports: dict
    table1: str
    ablation: str
    classes: str
    zoo: str
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


def first_ready(tasks: Sequence[Task], waiting: Sequence[int], done: set[str]) -> int | None:
    """The first of the ``waiting`` task indices (in list order) whose ``after`` tasks are all ``done``; None when
    none is ready."""
    return next((i for i in sorted(waiting) if all(name in done for name in tasks[i].after)), None)


def run_tasks(tasks: list[Task], jobs: int, say: Callable[[str], None]) -> tuple[list, list[StageTime]]:
    """Values and times of the tasks, in ``tasks`` order. A task's ``after`` names earlier tasks only (ValueError
    otherwise). ``jobs`` > 1: that many spawned processes run them at once, each with ``cpu_count // jobs`` torch
    and numba threads (one training per core costs less CPU than one training on two cores:
    benchmarks/results/bench_suite.md); whenever a process is free it starts the first task in list order whose
    ``after`` tasks are done (:func:`first_ready`), so the list order is the priority: a bench row starts while
    other runs still train, and a task that becomes ready late (a training after its data) does not wait behind
    the cheaper tasks listed after it. ``jobs`` 1: one after the other here."""
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
        with ProcessPoolExecutor(max_workers=jobs, **pool_options(multiprocessing.get_context("spawn"))) as pool:
            waiting, running, done = list(range(len(tasks))), {}, set()
            while waiting or running:
                while len(running) < jobs and (i := first_ready(tasks, waiting, done)) is not None:
                    say(f"{tasks[i].name} (started)")
                    running[pool.submit(_timed, tasks[i], threads)] = i
                    waiting.remove(i)
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in finished:
                    i = running.pop(future)
                    results[i] = future.result()
                    done.add(tasks[i].name)
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
    split = Z.split_config(config)
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


def train_config(config: SuiteConfig, spec: RunSpec, dataset: Path, renditions: tuple[Path, ...] = ()) -> TrainConfig:
    """The TrainConfig of one run of the profile (``renditions``: the datasets of ``spec.also_trains_on``)."""
    return TrainConfig(
        out=run_dir(config, spec.name), epochs=config.epochs * spec.epochs_factor, batch_scenes=config.batch_scenes,
        seed=config.seed + spec.seed_offset, model_preset=config.model_preset, use_adapter=spec.use_adapter,
        voxel_size=config.voxel_size, use_coordinates=config.use_coordinates,
        voxel_geometry=config.voxel_geometry, surface_radius=spec.surface_radius, progress=False,
        data=DataConfig(dataset=dataset, num_classes=config.num_classes, pixels_per_view=config.pixels_per_view,
                        holdout_classes=spec.holdout_classes, loss_gaussians=config.loss_gaussians,
                        scene_cache_size=config.scene_cache_size, renditions=tuple(renditions),
                        off_surface_augment=spec.off_surface_augment, colour_augment=spec.colour_augment),
        loss=LossConfig(no_3dt_align=spec.no_3dt_align, no_vs_align=spec.no_vs_align,
                        class_balance=config.class_balance, lovasz_weight=config.lovasz_weight,
                        opacity_power=config.opacity_power, unlabelled_as_unseen=spec.unlabelled_as_unseen),
        optim=OptimConfig(lr=config.lr),
    )


def train_run(config: SuiteConfig, spec: RunSpec, dataset: Path, renditions: tuple[Path, ...] = ()) -> Path:
    """Train one run (resumed when interrupted, reused when finished)."""
    run_config = train_config(config, spec, dataset, renditions)
    run = run_config.out
    done = run / "suite-done.json"
    data = {str(path): dataset_fingerprint(path) for path in (dataset, *renditions)}
    record = json.loads(done.read_text()) if done.is_file() else {}
    if record.get("epochs") == run_config.epochs:
        # a recipe changed in the code since (the folder's settings are checked by check_settings), or data rebuilt
        # since (a record without "data" was written before it was kept), is not reused
        changed = changed_settings(json.loads((run / CONFIG_NAME).read_text()), run_config)
        changed += ["its training data"] if record.get("data", data) != data else []
        if changed:
            raise ValueError(f"{run}: finished with another recipe or data than this version's run {spec.name!r} "
                             f"({', '.join(changed)}); use a new --out, or remove that run folder to retrain it")
        return run
    train(replace(run_config, resume=latest_checkpoint(run) is not None))
    write_json_atomic(done, {"epochs": run_config.epochs, "data": data})
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


def scored_weights(bench: BenchConfig) -> list[str | None]:
    """sha256 of the weights a model row scores now: its run's latest checkpoint, each ensemble member's, then its
    stacking calibration run's (when it has one)."""
    runs = (bench.run, *bench.ensemble_runs, *([bench.stacking_run] if bench.stacking_run is not None else []))
    return [weights_sha256(latest_checkpoint(run)) for run in runs]


def recorded_weights(payload: dict) -> list[str | None]:
    """sha256 of the weights a bench report scored, in :func:`scored_weights`' order."""
    predictor = payload.get("predictor", {})
    stacking = [predictor["stacking"].get("checkpoint_sha256")] if "stacking" in predictor else []
    return ([predictor.get("checkpoint_sha256")] + [m.get("checkpoint_sha256") for m in predictor.get("ensemble", [])]
            + stacking)


def bench_row(config: SuiteConfig, bench: BenchConfig, report_path: Path) -> dict:
    """The bench JSON payload of one row: reused when its report exists, scored the dataset as it is now and, for a
    model, the weights its runs hold now (a dataset rebuilt or a run retrained since is scored again)."""
    if report_path.is_file():
        payload = json.loads(report_path.read_text())
        fingerprint = dataset_fingerprint(bench.dataset)
        same_data = all(payload.get("dataset", {}).get(k) == v for k, v in fingerprint.items())
        if same_data and (bench.predictor != "model" or recorded_weights(payload) == scored_weights(bench)):
            return payload
    payload = run_bench(bench).payload
    write_json_atomic(report_path, payload)
    return payload


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


# --- the profile --------------------------------------------------------------------------------------


#: The settings a profile folder was made with (written on its first run, compared on every later one).
SETTINGS_NAME = "suite-settings.json"
#: SuiteConfig fields that change no result: where it is written, the progress display, processes at a time, and
#: whether the ensemble rows and the splat zoo are scored too (they add runs and rows, and change none that exist).
SETTINGS_IGNORED = ("out", "progress", "jobs", "ensemble", "zoo")
#: SuiteConfig fields added after profile folders were first made, with the value every folder made before had.
SETTINGS_ADDED = {"lovasz_weight": 0.0, "voxel_geometry": False, "opacity_power": 0.0, "zoo_fit_iterations": 600}


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

    if config.zoo and config.splats != "fit":
        raise ValueError("bench-suite --zoo: the splat zoo compares renditions of fitted rooms; it needs --splats fit")
    data = stage("data: synth + fit + build + split", build_data, config)
    dataset = data.splats
    datasets = Z.zoo_datasets(config, data.splats, data.oracle)
    sizes = split_sizes(dataset)
    rows = table1_rows(config)
    needed = {name for row in rows for name in row_runs(row)}
    if config.ablation:
        needed |= {row.run for row in ABLATION_ROWS}
    if config.zoo:
        needed |= {Z.RECIPE_RUN} | {r.matched_run for r in ZOO_RENDITIONS}
    specs = [spec for spec in RUNS + ZOO_RUNS if spec.name in needed]
    runs = {spec.name: run_dir(config, spec.name) for spec in specs}
    # one queue: the zoo's renditions, the trainings (longest first), then each bench row as soon as the runs it
    # scores (and the rendition it scores them on) are done
    built = tuple(r.name for r in ZOO_RENDITIONS if config.zoo and r.name not in ("splats", "oracle"))
    # the default-preset fits, the longest task of the zoo, in one slice of the rooms per process, then assembled
    slices = max(1, config.jobs) if "default-fit" in built else 0
    tasks = [Task(f"zoo: fit default-fit {i + 1}/{slices}", Z.build_rendition,
                  (config, "default-fit", data.splats, data.oracle, slices, i)) for i in range(slices if slices > 1 else 0)]
    fitted = tuple(task.name for task in tasks)
    tasks += [Task(f"zoo: build {name}", Z.build_rendition, (config, name, data.splats, data.oracle),
                   fitted if name == "default-fit" else ()) for name in built]
    tasks += [Task(f"train: {spec.name}", train_run,
                   (config, spec, datasets[spec.trained_on], tuple(datasets[r] for r in spec.also_trains_on)),
                   tuple(f"zoo: build {r}" for r in (spec.trained_on, *spec.also_trains_on) if r in built))
              for spec in specs]
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
    zoo_scorers = [(r, scorer) for r in ZOO_RENDITIONS for scorer in Z.ZOO_SCORERS] if config.zoo else []
    for r, scorer in zoo_scorers:
        run = {"recipe": Z.RECIPE_RUN, "matched": r.matched_run}.get(scorer)
        bench = replace(bench_config(config, datasets[r.name], run=None if run is None else runs[run],
                                     metrics=tuple(m for _, m, _ in Z.ZOO_METRICS)),
                        dims=("3d",), predictor="model" if run else scorer)
        tasks.append(Task(f"bench: zoo {r.name} {scorer}", bench_row,
                          (config, bench, reports_dir / f"zoo-{r.name}-{scorer}.json"),
                          tuple(f"train: {n}" for n in [run] if n) + tuple(f"zoo: build {n}" for n in [r.name] if n in built)))
    values, task_times = run_tasks(tasks, config.jobs, stamped)
    times += task_times
    by_task = {task.name: value for task, value in zip(tasks, values)}
    reports = {row.label: by_task[f"bench: {row.label}"] for row in rows}
    extra = {name: by_task[f"bench: ablation {name}"] for name in ablation_only}
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
    zoo_table = ""
    if config.zoo:
        zoo_reports: dict = {}
        for r, scorer in zoo_scorers:
            zoo_reports.setdefault(r.name, {})[scorer] = by_task[f"bench: zoo {r.name} {scorer}"]
        cells = Z.zoo_cells(zoo_reports)
        gaussians = {r.name: Z.scored_gaussians(datasets[r.name]) for r in ZOO_RENDITIONS}
        zoo_table = Z.format_zoo(cells, gaussians)
        result.update(Z.zoo_checks(cells, gaussians))
        Z.write_zoo_summary(out / "zoo.json", cells, gaussians)
        write_text_atomic(out / "zoo.md", zoo_table)
    wall, cpu = time.perf_counter() - started[0], _cpu_seconds() - started[1]
    invocation = {"times": [t._asdict() for t in times],
                  "total": {"wall_s": wall, "cpu_s": cpu, "load_average_start": load_at_start,
                            "load_average_end": list(os.getloadavg()), "cores": os.cpu_count(),
                            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}}
    summary = {
        "config": config_to_dict(config),
        "splits": sizes,
        "runs": {spec.name: config_to_dict(train_config(config, spec, datasets[spec.trained_on],
                                                        tuple(datasets[r] for r in spec.also_trains_on)))
                 for spec in specs},
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
                       classes, zoo_table, result, tuple(times), wall, cpu)
