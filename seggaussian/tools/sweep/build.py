"""The build stage sweep: executors, job counts and the cache, all of which must give byte-identical shards.

Quality = 1 when the Parquet shards equal those of the first (jobs 1, fresh folder) build, else 0; seconds per
scene is the cost. Builds use oracle Gaussians (fitting is swept apart).
"""

from __future__ import annotations

import hashlib
import shutil
import time
from dataclasses import replace
from pathlib import Path

from seggaussian.pipeline.scene import STAGES as BUILD_STAGES
from seggaussian.pipeline.dataset import build_dataset
from seggaussian.pipeline.config import BuildConfig, ViewConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.sources.layout import source_of_tree
from seggaussian.tools.sweep.pareto import Trial
from seggaussian.tools.sweep.config import StageSweepConfig
from seggaussian.tools.sweep.data import Progress, work_dir


def shards_digest(dataset: Path) -> str:
    """sha256 over the relative paths and bytes of the dataset's Parquet files (the cache excluded)."""
    h = hashlib.sha256()
    for path in sorted(p for p in Path(dataset).rglob("*.parquet") if ".build" not in p.relative_to(dataset).parts):
        h.update(str(path.relative_to(dataset)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def ray_available() -> bool:
    """Whether Ray (optional) imports."""
    try:
        import ray  # noqa: F401  (optional heavy dependency: imported only to test for it)
    except ImportError:
        return False
    return True


def sweep_build(config: StageSweepConfig, tasks: list, root: Path,
                progress: Progress | None = None) -> tuple[list, list]:
    """(rows, skipped) of the build sweep over ``tasks`` of the raw tree ``root``."""
    sweep = config.build
    shipped = BuildConfig(source="synthetic", root=root, out=root)
    skipped, trials = [], []
    reference_digest = None
    for executor in sweep.executors:
        if executor == "ray" and not ray_available():
            skipped.append("executor ray: Ray is not installed (pip install ray)")
            continue
        for jobs in sweep.jobs:
            out = work_dir(config) / "build-sweep" / f"{executor}-j{jobs}"
            if out.exists():
                shutil.rmtree(out)
            bcfg = BuildConfig(source=source_of_tree(root), root=root, out=out, scenes=tuple(t.scene_id for t in tasks),
                               jobs=jobs, executor=executor, gaussians="oracle", progress=False,
                               synthesize_missing=False, seed=config.seed,
                               oracle=replace(OracleConfig(), num_gaussians=sweep.num_gaussians),
                               views=replace(ViewConfig(), max_image_side=sweep.max_image_side))
            for cache in sorted(set(sweep.cache)):  # False (fresh folder) first, then the unchanged rerun
                if not cache and (out / ".build").exists():
                    shutil.rmtree(out)
                if progress:
                    progress(f"build executor={executor} jobs={jobs} cache={'on' if cache else 'off'}")
                t0 = time.perf_counter()
                report = build_dataset(bcfg)
                seconds = time.perf_counter() - t0
                digest = shards_digest(out)
                if reference_digest is None:
                    reference_digest = digest
                n = len(report.outcomes)
                per_scene = [scene_row(o) for o in report.outcomes]
                failed = sum(o.status == "failed" for o in report.outcomes)
                metrics = {"scenes": n, "failed": failed,
                           "scenes_per_minute": 60.0 * n / seconds if seconds > 0 else None,
                           "stages_cached": sum(len(p["stages_cached"]) for p in per_scene),
                           "stages_run": sum(len(p["stages_run"]) for p in per_scene),
                           "shards_rewritten": bool(report.assembled), "per_scene": per_scene}
                settings = {"executor": executor, "jobs": jobs, "cache": "on" if cache else "off"}
                quality = 1.0 if digest == reference_digest and not failed else 0.0
                is_default = (executor == shipped.executor and jobs == shipped.jobs and cache)
                first = trials[0].settings if trials else settings
                knob = "+".join(k for k in settings if settings[k] != first[k]) or "base"
                trials.append(Trial("build", knob, settings, seconds / max(n, 1), quality, metrics, is_default))
    return trials, skipped


def scene_row(outcome) -> dict:
    """One scene of a build row: what ran, what was cached, views stored, Gaussians left unlabelled."""
    info = outcome.info or {}
    tr = info.get("transfer", {})
    return {
        "scene": outcome.scene_id, "status": outcome.status, "stages_run": list(outcome.stages_run),
        "stages_cached": [s for s in BUILD_STAGES if s not in outcome.stages_run and outcome.status != "failed"],
        "views_stored": info.get("num_views"),
        "gaussians": info.get("num_gaussians"),
        "gaussians_ignored": tr.get("ignored"),
        "gaussians_outside_box": tr.get("outside_box"),
        "gaussians_beyond_gate": tr.get("beyond_gate"),
        "reason": outcome.reason,
    }
