"""Synthetic scenes written in the real ScanNet++ or Replica on-disk layouts (the default data).

``synthesize(out, num_scenes, seed, layout)`` builds procedural furnished rooms (``room``),
a capture path (``camera_path``), renders RGB + ground-truth labels by raycasting and writes every
file of the layout (``scannetpp`` / ``replica`` of this package). Output bytes depend only on
(seed, scene index, layout, config). Each scene is written into a hidden temporary folder and
renamed into place, so an interrupted run leaves no half-written scene behind.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import shutil
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from seggaussian.util.atomic import make_dirs, sweep_temps, temp_name
from seggaussian.core.cameras import Camera
from seggaussian.sources.synthetic import replica as synth_replica
from seggaussian.sources.synthetic import scannetpp as synth_scannetpp
from seggaussian.sources.camera_path import default_intrinsics, generate_camera_path
from seggaussian.sources.replica import nice_slam_intrinsics
from seggaussian.sources.synthetic.replica import replica_size
from seggaussian.sources.synthetic.mesh import RoomConfig, RoomMesh
from seggaussian.sources.synthetic.room import build_room
from seggaussian.util.workers import pool_options

LAYOUTS = ("scannetpp", "replica")


@dataclass(frozen=True)
class SynthConfig:
    """What ``synthesize`` writes per scene."""

    width: int = 320
    """Image width in pixels (ScanNet++ height = 3/4 of it; Replica height keeps the 1200x680 aspect)."""
    num_views: int = 32
    """Views per scene along the capture path (every 8th is a novel/test view)."""
    max_edge: float = 0.05
    """Longest mesh edge in metres (vertex colours carry texture at this resolution)."""
    focal_factor: float = 0.6
    """ScanNet++ layout: fx = fy = focal_factor * width (about 80 degrees horizontal field of view)."""
    height: int | None = None
    """ScanNet++ layout: image height in pixels; None: 3/4 of the width (876 x 584 is the size of ScanNet++'s
    undistorted DSLR images)."""


def scene_name(seed: int, index: int, layout: str) -> str:
    """ScanNet++: a 10-hex-digit id like the real ones; Replica: ``synroomN_sS``."""
    if layout == "replica":
        return f"synroom{index}_s{seed}"
    return hashlib.sha1(f"seggaussian-synthetic-{seed}-{index}".encode()).hexdigest()[:10]


def scene_rng(seed: int, index: int, layout: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(index), LAYOUTS.index(layout)])


def build_scene(seed: int, index: int, layout: str, config: SynthConfig = SynthConfig()) -> tuple[RoomMesh, list[Camera]]:
    """The room and cameras of scene ``index`` (what ``synthesize`` writes; used by tests as truth)."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    rng = scene_rng(seed, index, layout)
    room = build_room(rng, RoomConfig(max_edge=config.max_edge, style=layout))
    if layout == "replica":
        width, height = replica_size(config.width)
        K = nice_slam_intrinsics(width, height)
    else:
        width, height = config.width, config.height or int(round(config.width * 3 / 4))
        K = default_intrinsics(width, height, config.focal_factor)
    cameras = generate_camera_path(room.room_min, room.room_max, config.num_views, K, width, height, rng)
    return room, cameras


def synthesize(
    out: Path | str,
    num_scenes: int,
    seed: int,
    layout: str = "scannetpp",
    config: SynthConfig = SynthConfig(),
    progress: Callable[[int, str], None] | None = None,
    jobs: int = 1,
) -> list[str]:
    """Write ``num_scenes`` scenes under ``out`` in ``layout``; returns their scene ids (in index order).

    ScanNet++: ``out`` becomes a DATA_ROOT (``data/``, ``metadata/``, ``splits/``).
    Replica: ``out/<room>/`` per scene.
    ``jobs`` > 1: that many spawned processes write scenes at once (the bytes do not depend on it); ``progress``
    is then called as scenes finish, in any order.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if num_scenes < 0:
        raise ValueError(f"num_scenes must be >= 0, got {num_scenes}")
    if config.width < 16 or config.num_views < 1 or not config.max_edge > 0 or (config.height or 16) < 16:
        raise ValueError(f"invalid SynthConfig {config}")
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    out = Path(out)
    scene_parent = out / "data" if layout == "scannetpp" else out
    make_dirs(scene_parent)
    sweep_temps(scene_parent)  # staging folders of a killed earlier run
    ids: list[str] = [scene_name(seed, index, layout) for index in range(num_scenes)]
    if jobs == 1 or num_scenes <= 1:
        for index in range(num_scenes):
            write_scene(scene_parent, seed, index, layout, config)
            if progress is not None:
                progress(index, ids[index])
    else:
        # spawn: open3d's and numba's threads do not survive fork
        with ProcessPoolExecutor(max_workers=jobs, **pool_options(multiprocessing.get_context("spawn"))) as pool:
            futures = {pool.submit(write_scene, scene_parent, seed, index, layout, config): index
                       for index in range(num_scenes)}
            for future in as_completed(futures):
                future.result()
                if progress is not None:
                    progress(futures[future], ids[futures[future]])
    if layout == "scannetpp":
        synth_scannetpp.write_metadata(out, ids)
    else:
        synth_replica.write_root_files(out, ids)
    return ids


def write_scene(scene_parent: Path, seed: int, index: int, layout: str, config: SynthConfig) -> str:
    """Write scene ``index`` as ``scene_parent/<its id>`` (staged in a hidden folder, renamed into place);
    returns its id."""
    name = scene_name(seed, index, layout)
    room, cameras = build_scene(seed, index, layout, config)
    staging = temp_name(scene_parent / name)
    if layout == "scannetpp":
        # writers take the folder that holds data/<id>; stage under a private DATA_ROOT
        synth_scannetpp.write_scene(staging, name, room, cameras)
        _move_into_place(staging / "data" / name, scene_parent / name)
    else:
        synth_replica.write_scene(staging, name, room, cameras)
        _move_into_place(staging / name, scene_parent / name)
    shutil.rmtree(staging)
    return name


def _move_into_place(source: Path, target: Path) -> None:
    """Rename a finished scene folder onto ``target`` (replacing an older one)."""
    old = temp_name(target)
    if target.exists():
        os.replace(target, old)
    os.replace(source, target)
    if old.exists():
        shutil.rmtree(old)
