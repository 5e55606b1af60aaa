"""Executors of ``seggaussian build``: scenes built in this process, in a spawned process pool, or on Ray
(``ray_tasks``)."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.ray_tasks import run_ray
from seggaussian.pipeline.scene import build_scene
from seggaussian.pipeline.records import SceneOutcome, SceneTask, crashed_outcome
from seggaussian.util.threads import cap_threads
from seggaussian.util.workers import pool_options


def _worker(task: SceneTask, config: BuildConfig, cache_root: Path, threads: int) -> SceneOutcome:
    """Process-pool / Ray entry point: cap torch's and numba's threads (``cap_threads``), then build one scene."""
    cap_threads(threads)
    return build_scene(task, config, cache_root)


def run_tasks(tasks: list[SceneTask], config: BuildConfig, cache_root: Path,
              on_done) -> tuple[list[SceneOutcome], list]:
    """Build every task with the configured executor; ``on_done(outcome)`` is called as scenes finish.
    Returns the outcomes and, for Ray, the nodes that passed the storage check (``ray_tasks.NodeCheck``)."""
    outcomes: list[SceneOutcome] = []
    if config.executor == "ray":
        return run_ray(tasks, config, cache_root, on_done, _worker)
    if config.executor != "local":
        raise ValueError(f"build: --executor must be local or ray, got {config.executor!r}")
    jobs = max(1, int(config.jobs))
    threads = max(1, (os.cpu_count() or 1) // jobs)
    if jobs == 1 or len(tasks) <= 1:
        for t in tasks:
            outcome = build_scene(t, config, cache_root)
            outcomes.append(outcome)
            on_done(outcome)
        return outcomes, []
    # spawn: numba's OpenMP layer and torch threads do not survive fork
    with ProcessPoolExecutor(max_workers=jobs, **pool_options(multiprocessing.get_context("spawn"))) as pool:
        futures = {pool.submit(_worker, t, config, cache_root, threads): t for t in tasks}
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except Exception as exc:  # noqa: BLE001 -- a crashed worker fails its scene only
                outcome = crashed_outcome(futures[future], exc)
            outcomes.append(outcome)
            on_done(outcome)
    return outcomes, []
