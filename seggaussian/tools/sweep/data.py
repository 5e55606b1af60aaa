"""The data of a stage sweep: the raw tree (given, or the default synthetic set synthesized once), its scenes,
the oracle Gaussians that carry their true label, and the machine the rows were timed on.

Ground truth always comes from the labelled mesh (or held-out views), never from the stage under test.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from seggaussian.util.atomic import atomic_dir, sweep_temps, write_text_atomic
from seggaussian.pipeline.config import BuildConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.pipeline.discover import discover
from seggaussian.labels.oracle import sample_oracle_gaussians
from seggaussian.util.seeds import scene_seed
from seggaussian.sources.layout import reader, source_of_tree
from seggaussian.sources.synthetic.generate import SynthConfig, synthesize
from seggaussian.tools.sweep.config import StageSweepConfig

#: Marker file written into a synthesized set once every scene is in place.
SYNTH_DONE_MARKER = ".stage-bench-complete"

Progress = Callable[[str], None]


class SweepDataError(ValueError):
    """A stage sweep cannot use the given data; the message names the path and what is missing."""


def work_dir(config: StageSweepConfig) -> Path:
    return Path(config.work_dir).expanduser()


def prepare_data(config: StageSweepConfig, progress: Progress | None = None) -> Path:
    """The raw tree to sweep: ``config.data``, or the default synthetic set synthesized (once) into
    ``config.work_dir`` (written to a temporary folder, then renamed; temporaries of a killed run swept)."""
    if config.data is not None:
        root = Path(config.data)
        if not root.is_dir():
            raise SweepDataError(f"{root}: --data does not exist or is not a folder")
        if (root / "manifest.json").is_file() or (root / ".build").is_dir():
            raise SweepDataError(f"{root}: this is a built DATASET; the stage sweep needs the raw tree it was built "
                                 "from (meshes are the ground truth)")
        return root
    n_scannetpp, n_replica = config.synthetic_counts
    name = (f"synthetic-s{config.seed}-w{config.synthetic_width}-v{config.synthetic_views}"
            f"-e{config.synthetic_max_edge:g}-{n_scannetpp}x{n_replica}")
    root = work_dir(config) / name
    if (root / SYNTH_DONE_MARKER).is_file():
        return root
    sweep_temps(root.parent)  # staging folders of a killed earlier run
    synth = SynthConfig(width=config.synthetic_width, num_views=config.synthetic_views,
                        max_edge=config.synthetic_max_edge)
    with atomic_dir(root) as staging:
        for layout, count in (("scannetpp", n_scannetpp), ("replica", n_replica)):
            if count > 0:
                if progress:
                    progress(f"synthesizing {count} {layout} scenes into {root}")
                synthesize(staging / layout, count, config.seed, layout=layout, config=synth)
        write_text_atomic(staging / SYNTH_DONE_MARKER, "ok\n")
    return root


def discover_scenes(root: Path, config: StageSweepConfig) -> list:
    """``build.SceneTask`` rows of the raw tree (at most ``config.scenes``)."""
    tasks, failures = discover(BuildConfig(source=source_of_tree(root), root=root, out=work_dir(config) / "unused",
                                           synthesize_missing=False, progress=False))
    if failures:
        raise SweepDataError(f"{root}: " + "; ".join(f"{f.scene_id}: {f.reason}" for f in failures))
    if not tasks:
        raise SweepDataError(f"{root}: no scene found (expected a ScanNet++ or Replica layout)")
    return tasks[: config.scenes] if config.scenes else tasks


def read_task_scene(task, config: StageSweepConfig):
    """The ``Scene`` of a task (Replica rooms without views are rendered into the work folder)."""
    if task.domain == "replica":
        return reader("replica").read_scene(task.root, task.scene_id, cache_dir=work_dir(config) / "replica_views")
    return reader(task.domain).read_scene(task.root, task.scene_id)


def require_mesh(scene, stage: str) -> None:
    if scene.faces is None or not len(scene.faces):
        raise SweepDataError(f"scene {scene.scene_id} ({scene.root}): the {stage} sweep needs a labelled mesh "
                             "(faces) as ground truth; this scene is a point cloud")


def oracle_labelled(scene, num_gaussians: int, seed: int):
    """(oracle Gaussians, true class [N]) sampled on the scene's visible labelled triangles."""
    rng = np.random.default_rng(scene_seed(seed, scene.scene_id))
    return sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces,
                                   replace(OracleConfig(), num_gaussians=int(num_gaussians)), rng,
                                   tuple(v.camera for v in scene.views))


def machine_info() -> dict:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    cpus = os.cpu_count() or 1
    return {"cpus": cpus, "load_average_1min": load[0], "under_load": bool(load[0] > 0.5 * cpus)}
