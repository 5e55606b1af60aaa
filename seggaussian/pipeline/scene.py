"""One scene through the build's stage chain, each stage served from the cache when its key is unchanged.

    gaussians  stages.gaussians_{oracle,scan,fit,import}  -> gaussians_stage.parquet
    transfer   stages.transfer                            -> gaussians.parquet (the scene's gaussians table)
    views      stages.views                               -> views.parquet (the scene's views table)

Outputs live in ``DATASET/.build/scenes/<scene>/`` with a record ``<stage>.json`` per stage
(``build_cache.StageRecord``); a stage runs only when its key changed or an output is missing. Once assembled, the
two tables are rows of the shards, and the scene's ``shards.json`` points at them (``fragments``): the transfer and
views stages are cached while the shard still holds their rows.
"""

from __future__ import annotations

import os
import time
import traceback
from dataclasses import asdict
from pathlib import Path

import numpy as np

from seggaussian.pipeline import cache as build_cache
from seggaussian.pipeline import fragments
from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.records import CpuClock, SceneOutcome, SceneTask, failed_outcome
from seggaussian.core.constants import read_class_names
from seggaussian.fit.optimize import needs_fit
from seggaussian.shards.rows import read_fragment_rows
from seggaussian.sources.layout import reader
from seggaussian.pipeline.stages import gaussians as gaussians_stage
from seggaussian.pipeline.stages import gaussians_fit, gaussians_import, gaussians_oracle, gaussians_scan
from seggaussian.pipeline.stages import transfer as transfer_stage
from seggaussian.pipeline.stages import views as views_stage

STAGES = ("gaussians", "transfer", "views")
#: The module of each mode of the gaussians stage (``gaussians_stage_config``'s ``mode``).
GAUSSIANS_MODES = {"oracle": gaussians_oracle, "scan": gaussians_scan, "fit": gaussians_fit,
                   "import": gaussians_import}
#: The entry module of the transfer and views stages (the gaussians stage's depends on its mode).
STAGE_MODULES = {"transfer": transfer_stage.__name__, "views": views_stage.__name__}
OUTPUTS = {"gaussians": gaussians_stage.OUTPUTS, "transfer": transfer_stage.OUTPUTS, "views": views_stage.OUTPUTS}


def gaussians_stage_config(config: BuildConfig, task: SceneTask) -> dict:
    """What the gaussians stage depends on: its mode, the fitting/oracle settings, the trained PLY's stat."""
    if config.gaussians == "oracle":
        return {"mode": "oracle", "oracle": asdict(config.oracle), "seed": config.seed}
    if config.gaussians == "scan":  # every vertex: the key of builds before the cap existed
        cap = config.scan_max_gaussians
        return {"mode": "scan"} if cap is None else {"mode": "scan", "max_gaussians": cap, "seed": config.seed}
    if config.source == "ply" and task.trained_ply is None:
        raise FileNotFoundError(f"--source ply: no trained PLY for scene {task.scene_id} in {config.ply_dir}")
    if needs_fit(config.fit, task.trained_ply):
        return {"mode": "fit", "fit": asdict(config.fit_config), "seed": config.seed}
    if task.trained_ply is None:
        raise FileNotFoundError(f"--fit never: no trained PLY for scene {task.scene_id}")
    st = task.trained_ply.stat()
    return {"mode": "import", "ply": [str(task.trained_ply), st.st_size, st.st_mtime_ns],
            "frame": gaussians_import.frame_key(task.transform_file)}


def stage_keys(task: SceneTask, config: BuildConfig, g_cfg: dict, num_classes: int) -> tuple[dict, dict]:
    """({stage: key}, {stage: what the key was made of}); each key chains the upstream stage's key."""
    code = {"gaussians": build_cache.code_digest(GAUSSIANS_MODES[g_cfg["mode"]].__name__),
            **{name: build_cache.code_digest(module) for name, module in STAGE_MODULES.items()}}
    parts = {
        "gaussians": [task.fingerprint, g_cfg, code["gaussians"]],
        "transfer": [task.fingerprint, asdict(config.transfer), code["transfer"]],
        "views": [asdict(config.views), num_classes, code["views"]],
    }
    keys = {"gaussians": build_cache.sha256_json(parts["gaussians"])}
    keys["transfer"] = build_cache.sha256_json([keys["gaussians"], *parts["transfer"]])
    keys["views"] = build_cache.sha256_json([keys["transfer"], *parts["views"]])
    return keys, parts


def build_scene(task: SceneTask, config: BuildConfig, cache_root: Path) -> SceneOutcome:
    """Run the scene's stages that are not cached. Never raises: a failure is returned with its reason."""
    start = time.perf_counter()
    try:
        return _build_scene(task, config, cache_root, start)
    except Exception as exc:  # noqa: BLE001 -- one bad scene must not stop the others
        return failed_outcome(task, f"{type(exc).__name__}: {exc}", time.perf_counter() - start,
                              trace=traceback.format_exc() if os.environ.get("SEGGAUSSIAN_DEBUG") else None)


def _build_scene(task: SceneTask, config: BuildConfig, cache_root: Path, start: float) -> SceneOutcome:
    scene_dir = cache_root / "scenes" / task.scene_id
    scene_dir.mkdir(parents=True, exist_ok=True)
    class_names = read_class_names()
    g_cfg = gaussians_stage_config(config, task)
    keys, parts = stage_keys(task, config, g_cfg, len(class_names))
    stages = {name: build_cache.StageRecord(scene_dir, name) for name in STAGES}
    records = {name: stages[name].cached(keys[name], OUTPUTS[name] if name == "gaussians" else ()) for name in STAGES}
    dataset = cache_root.parent
    files = {table: scene_dir / OUTPUTS[stage][0] for stage, table in fragments.STAGE_TABLES.items()}
    pointers = fragments.read_pointers(scene_dir)
    tables = {}  # {table: its per-scene file, or its rows in a shard}
    for stage, table in fragments.STAGE_TABLES.items():
        if records[stage] is not None:
            tables[table] = fragments.cached(dataset, files[table], pointers.get(table), keys[stage])
            if tables[table] is None:
                records[stage] = None
    ran: list[str] = []
    clock = CpuClock()  # CPU seconds per stage (its reads and writes included), the scene's reading and occlusion apart
    scene = None
    gaussians = truth = labelled = None

    def get_scene():
        nonlocal scene
        if scene is None:
            with clock.measure("read"):
                if task.domain == "replica":  # rooms without pre-rendered views are rendered into the cache
                    scene = reader("replica").read_scene(task.root, task.scene_id,
                                                         cache_dir=cache_root / "replica_views")
                else:
                    scene = reader(task.domain).read_scene(task.root, task.scene_id)
        return scene

    if records["gaussians"] is None:
        with clock.measure("gaussians"):
            gaussians, truth, facts = GAUSSIANS_MODES[g_cfg["mode"]].run(
                get_scene(), config, scene_dir, task.trained_ply,
                **({"transform_file": task.transform_file} if g_cfg["mode"] == "import" else {}))
        facts["num_gaussians"] = len(gaussians)
        stages["gaussians"].save(keys["gaussians"], facts, parts["gaussians"])
        records["gaussians"] = {"info": facts}
        ran.append("gaussians")
    if records["transfer"] is None:
        with clock.measure("transfer"):
            if gaussians is None:
                gaussians, truth = gaussians_stage.load_gaussians(scene_dir)
            labelled, facts = transfer_stage.run_transfer(get_scene(), gaussians, truth, config,
                                                          refuse_misplaced=g_cfg["mode"] == "import", clock=clock)
            with clock.measure("shards"):
                transfer_stage.write_transfer(scene_dir, task.scene_id, labelled, config.shards)
        tables[fragments.STAGE_TABLES["transfer"]] = files[fragments.STAGE_TABLES["transfer"]]
        stages["transfer"].save(keys["transfer"], facts, parts["transfer"])
        records["transfer"] = {"info": facts}
        ran.append("transfer")
    if records["views"] is None:
        with clock.measure("views"):
            if labelled is None:
                if gaussians is None:
                    gaussians, _ = gaussians_stage.load_gaussians(scene_dir)
                source = tables["gaussians"]
                labels = read_fragment_rows(dataset, source, "gaussians", list(transfer_stage.LABEL_COLUMNS))
                labelled = transfer_stage.with_labels(gaussians, labels, fragments.location(dataset, source))
            rows, facts = views_stage.run_views(get_scene(), labelled, config, len(class_names))
            with clock.measure("shards"):
                views_stage.write_views(scene_dir, task.scene_id, rows, config.shards)
        tables[fragments.STAGE_TABLES["views"]] = files[fragments.STAGE_TABLES["views"]]
        stages["views"].save(keys["views"], facts, parts["views"])
        records["views"] = {"info": facts}
        ran.append("views")
    info = {"source": task.domain}
    for name in STAGES:
        info.update(records[name]["info"])
    if "fit_metrics" in info:  # JSON-safe: drop non-finite numbers
        info["fit_metrics"] = {k: v for k, v in info["fit_metrics"].items()
                               if not isinstance(v, float) or np.isfinite(v)}
    info["num_gaussians"] = info.get("transfer", {}).get("num_gaussians", info.get("num_gaussians", 0))
    return SceneOutcome(task.scene_id, task.domain, task.official_split, "built" if ran else "skipped", tuple(ran),
                        None, info, tables, keys, time.perf_counter() - start, clock.rounded())
