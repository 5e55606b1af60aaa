"""``seggaussian build``: raw scenes -> labelled Gaussians -> per-view label maps -> split-named Parquet shards.

Orchestration only; every step is a call into its own module:

    discover   build_discover: the scenes of the raw tree (sources.layout) + a fingerprint of each one's raw files
    per scene  build_scene: the stage chain, each stage served from the cache when its key is unchanged
                 gaussians  stages.gaussians_{oracle,fit,import} (oracle.py | fit.py | io.formats)
                 transfer   stages.transfer (transfer.py)  -> per-scene ``gaussians`` table
                 views      stages.views (render/)         -> per-scene ``views`` table
    executors  build_executors: in process, a spawned process pool, or Ray (ray_tasks)
    assemble   build_record: the build record, split.assign_splits + shards.write_dataset

``--num-shards N --shard-index K`` builds one slice of the scenes (``slicing``) and stops before the
build record and the assembly; slices run at once into one output, and a later build without slicing
assembles them.

Cache (``DATASET/.build/scenes/<scene>/``): each stage writes its outputs atomically, then a record
``<stage>.json`` holding the stage key = sha256 of (input fingerprint, upstream keys, the stage's config,
the source of every module the stage's code imports: ``build_cache``). A stage runs only when its key changed or an
output is missing, so an unchanged rerun reads no raw scene and writes no file; a changed setting reruns the stages
downstream of it; a killed build resumes at the first stage without a record. Outputs are byte-deterministic for
the same inputs and config. Once assembled, a scene's two tables leave the cache: a pointer at its rows in the
shards replaces them (``fragments``), and a later assembly copies the rows from there.

``--source synthetic``: ``ROOT/scannetpp`` (ScanNet++ layout) and ``ROOT/replica`` (Replica layout), as
written by ``seggaussian synth``; a root holding only one layout is read as that layout. When ``ROOT``
does not exist, the default synthetic set is synthesized into it first (``BuildConfig.synthesize_missing``).
"""

from __future__ import annotations

import errno
import time
from pathlib import Path

from seggaussian.util.atomic import ensure_writable_dir, sweep_temps
from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.discover import discover, synthesize_default
from seggaussian.pipeline.executors import run_tasks
from seggaussian.pipeline.assembly import CACHE_DIR, assemble, write_build_record
from seggaussian.pipeline.slicing import check_slice, slice_ids
from seggaussian.pipeline.scene import STAGES
from seggaussian.pipeline.records import BuildReport, CpuClock, SceneOutcome


def build_dataset(config: BuildConfig) -> BuildReport:
    """Build (or update) the dataset in ``config.out``; see the module docstring."""
    start = time.perf_counter()
    out = Path(config.out)
    cache_root = out / CACHE_DIR
    synthesized: list[str] = []
    check_slice(config.num_shards, config.shard_index)
    sliced = config.num_shards > 1
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "the output is not a folder", str(out))
    ensure_writable_dir(out)  # fail before building scenes, not after
    if config.source == "synthetic" and not Path(config.root).exists():
        if not config.synthesize_missing or sliced:  # slices would race to write one tree
            raise FileNotFoundError(f"{config.root}: no synthetic tree (write one with `seggaussian synth`)")
        synthesized = synthesize_default(config)
    if config.source == "ply" and config.ply_dir is None:
        raise ValueError("build: --source ply needs --ply-dir (trained PLYs)")
    clock = CpuClock()
    with clock.measure("discover"):
        tasks, failures = discover(config)
    if not tasks and not failures:
        raise ValueError(f"{config.root}: no scenes found in the raw tree (an empty source root is an error)")
    if sliced:
        keep = set(slice_ids([t.scene_id for t in tasks] + [f.scene_id for f in failures], config.num_shards,
                             config.shard_index))
        tasks = [t for t in tasks if t.scene_id in keep]
        failures = [f for f in failures if f.scene_id in keep]
        # other slices write beside this one: sweep only this slice's scene folders (a temporary's pid
        # says nothing about a writer on another machine)
        swept = _sweep_scene_folders(cache_root, tasks)
    else:
        swept = sweep_temps(out, recursive=True)  # leftovers of a killed earlier build
    bars = _progress_bars(len(tasks), config.progress)
    outcomes = list(failures)

    def on_done(outcome: SceneOutcome) -> None:
        for name, bar in bars.items():
            if bar is not None:
                bar.update(1)
                if name in outcome.stages_run:
                    bar.set_postfix_str(f"last ran: {outcome.scene_id}", refresh=False)

    try:
        done, nodes = run_tasks(tasks, config, cache_root, on_done)
        outcomes += done
    finally:
        for bar in bars.values():
            if bar is not None:
                bar.close()
    swept += _sweep_scene_folders(cache_root, tasks)  # what a worker lost mid-write (and then rerun) left
    outcomes.sort(key=lambda o: o.scene_id)
    if sliced:  # the dataset-level files are left to a build without slicing
        return BuildReport(out, outcomes, {}, 0, 0, False, synthesized, time.perf_counter() - start, (), swept,
                           clock.rounded(), (config.shard_index, config.num_shards), tuple(nodes))
    with clock.measure("assemble"):
        kept = write_build_record(cache_root, config, outcomes)
        split_counts, files, nbytes, assembled = assemble(out, config)
    return BuildReport(out, outcomes, split_counts, files, nbytes, assembled, synthesized,
                       time.perf_counter() - start, tuple(kept), swept, clock.rounded(), None, tuple(nodes))


def _sweep_scene_folders(cache_root: Path, tasks) -> int:
    """Sweep the temporaries whose writer is gone from the cache folders of ``tasks``' scenes only."""
    return sum(sweep_temps(cache_root / folder / t.scene_id, recursive=True) for folder in ("scenes", "replica_views")
               for t in tasks)


def _progress_bars(total: int, enabled: bool) -> dict:
    if not enabled or total == 0:
        return {name: None for name in STAGES}
    from tqdm import tqdm

    return {name: tqdm(total=total, desc=f"{name:9s}", unit="scene", position=i, leave=True)
            for i, name in enumerate(STAGES)}


def summary_table(report: BuildReport) -> str:
    """Plain-text table: one line per scene (status, stages run, Gaussians, views, ignored share, reason)."""
    lines = [f"{'scene':24s} {'split-src':10s} {'status':8s} {'stages':26s} {'gaussians':>10s} {'views':>6s} "
             f"{'ignored':>8s} {'acc':>6s}  reason"]
    for o in report.outcomes:
        t = o.info.get("transfer", {})
        acc = o.info.get("label_accuracy", {}).get("accuracy")
        lines.append(
            f"{o.scene_id:24s} {o.domain:10s} {o.status:8s} {','.join(o.stages_run) or '-':26s} "
            f"{o.info.get('num_gaussians', 0):>10d} {o.info.get('num_views', 0):>6d} "
            f"{t.get('ignored_share', 0.0):>8.3f} {'' if acc is None else f'{acc:.3f}':>6s}  "
            f"{(o.reason or '').splitlines()[0] if o.reason else ''}"
        )
    return "\n".join(lines)
