"""Executors of ``seggaussian build``: scenes built in this process, in a spawned process pool, or on Ray."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.scene import build_scene
from seggaussian.pipeline.records import SceneOutcome, SceneTask, failed_outcome
from seggaussian.util.threads import cap_threads


def _worker(task: SceneTask, config: BuildConfig, cache_root: Path, threads: int) -> SceneOutcome:
    """Process-pool / Ray entry point: cap torch's and numba's threads (``cap_threads``), then build one scene."""
    cap_threads(threads)
    return build_scene(task, config, cache_root)


def run_tasks(tasks: list[SceneTask], config: BuildConfig, cache_root: Path, on_done) -> list[SceneOutcome]:
    """Build every task with the configured executor; ``on_done(outcome)`` is called as scenes finish."""
    outcomes: list[SceneOutcome] = []
    jobs = max(1, int(config.jobs))
    threads = max(1, (os.cpu_count() or 1) // jobs)
    if config.executor == "ray":
        try:
            import ray
        except ImportError:
            raise RuntimeError("--executor ray needs Ray: pip install 'seggaussian[ray]' (or ray>=2.9)") from None
        if not ray.is_initialized():
            ray.init(address=config.address, include_dashboard=False, log_to_driver=False)
        remote = ray.remote(_worker)
        pending = [remote.remote(t, config, cache_root, threads) for t in tasks]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            outcome = ray.get(done[0])
            outcomes.append(outcome)
            on_done(outcome)
        return outcomes
    if config.executor != "local":
        raise ValueError(f"build: --executor must be local or ray, got {config.executor!r}")
    if jobs == 1 or len(tasks) <= 1:
        for t in tasks:
            outcome = build_scene(t, config, cache_root)
            outcomes.append(outcome)
            on_done(outcome)
        return outcomes
    # spawn: numba's OpenMP layer and torch threads do not survive fork
    with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(_worker, t, config, cache_root, threads): t for t in tasks}
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except Exception as exc:  # noqa: BLE001 -- a crashed worker fails its scene only
                outcome = failed_outcome(futures[future], f"worker crashed: {type(exc).__name__}: {exc}", 0.0)
            outcomes.append(outcome)
            on_done(outcome)
    return outcomes
