"""Frozen configuration of the dataset build: label transfer, oracle Gaussians, views, shards, split.

Kept apart from the code that uses it. Every field that changes a stage's output takes part in that
stage's cache key (``seggaussian.pipeline.scene.stage_keys``), so changing one setting reruns only the stages downstream of it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, Optional

from seggaussian.fit.config import FitConfig
from seggaussian.labels.config import OracleConfig, TransferConfig
from seggaussian.shards.config import ShardConfig


@dataclass(frozen=True)
class ViewConfig:
    """Per-view records: RGB, camera and label maps rendered through the rasterizer's blend weights."""

    #: Resize factor applied to every view (camera and image); 1.0 keeps the source size.
    image_scale: float = 1.0
    #: Longest image side after scaling is clamped to this (pixels); 0 = no clamp.
    max_image_side: int = 640
    #: Contributors kept per pixel by ``compute_blend_weights``.
    top_k: int = 16
    #: Pixels whose accumulated alpha is below this get IGNORE_LABEL in the label maps.
    min_alpha: float = 0.5
    #: Keep only every n-th view of a scene (1 = all views); novel views are always kept.
    view_stride: int = 1


@dataclass(frozen=True)
class SplitConfig:
    """train / val / xval assignment (``seggaussian.pipeline.split``)."""

    #: Paper ratio train, val, cross-domain (230/50/8). ScanNet++ scenes split train:val by the first
    #: two numbers; every Replica scene is cross-domain (xval), whatever the third number.
    ratios: tuple[int, int, int] = (230, 50, 8)
    #: Seed of the stable hash ordering.
    seed: int = 0
    #: Recompute every assignment instead of keeping those already in splits.json.
    reassign: bool = False


@dataclass(frozen=True)
class BuildConfig:
    """One ``seggaussian build`` run."""

    #: ``synthetic`` (RAW/scannetpp and/or RAW/replica trees written by ``seggaussian synth``),
    #: ``scannetpp``, ``replica`` or ``ply`` (trained PLYs in ``ply_dir`` + the raw scenes for labels).
    source: Literal["synthetic", "scannetpp", "replica", "ply"]
    #: Raw tree (read only).
    root: Path
    #: Dataset folder (shards, manifest, splits, and the build cache in ``.build/``).
    out: Path
    #: Scene ids to build (None = every scene the source lists).
    scenes: tuple[str, ...] | None = None
    #: Parallel scene workers.
    jobs: int = 1
    #: ``local`` (process pool, spawn) or ``ray``.
    executor: Literal["local", "ray"] = "local"
    #: Ray cluster address (None = start a local Ray). A loopback address (``127.0.0.1:PORT``) is kept as
    #: given: the driver then takes 127.0.0.1 as its own address too, as the nodes of such a cluster do.
    address: str | None = None
    #: CPUs each scene's Ray task asks for (it also caps the task's torch and numba threads).
    ray_cpus: float = 1.0
    #: Memory each scene's Ray task asks for (GiB); the scheduler places a scene only where this much is free.
    ray_memory_gb: float = 2.0
    #: Times Ray reruns a scene whose worker process or node was lost (an error raised by the scene is a
    #: failed scene, never retried: it would fail again).
    ray_retries: int = 3
    #: Seconds to wait for the Ray cluster: connecting, and every node's check of the raw root and the output.
    ray_timeout: float = 60.0
    #: Seconds a build waits for the next scene to finish on Ray; when none does, the scenes still running
    #: fail with this as their reason (0 = wait without limit).
    ray_scene_timeout: float = 0.0
    #: Slices of the sorted scene list for job arrays (each array task builds one slice into the same
    #: output; a later build without slicing finds every scene cached and assembles the dataset).
    num_shards: int = 1
    #: The slice this run builds: scenes whose position in the sorted scene ids is ``shard_index``
    #: modulo ``num_shards`` (0-based).
    shard_index: int = 0
    #: ``auto`` fits when no trained PLY exists, ``always`` refits, ``never`` requires a PLY.
    fit: Literal["auto", "always", "never"] = "auto"
    #: ``fit`` = optimized Gaussians (or imported PLY); ``oracle`` = sampled from the labelled mesh; ``scan`` = one
    #: isotropic Gaussian per mesh vertex with its colour (a scan turned into splats, no fit).
    gaussians: Literal["fit", "oracle", "scan"] = "fit"
    #: ``scan`` only: at most this many Gaussians per scene, a uniform draw of the vertices seeded by ``seed`` with
    #: scales from the kept ones' spacing (a sparser scanner; a cheaper rendition to train on). None: every vertex.
    scan_max_gaussians: Optional[int] = None
    #: Fitting settings for ``--gaussians fit`` when a scene needs fitting.
    fit_config: FitConfig = field(default_factory=FitConfig)
    #: Folder of trained PLYs for ``--source ply`` (``<scene>.ply`` or ``<scene>/point_cloud/iteration_*/point_cloud.ply``).
    ply_dir: Path | None = None
    #: Seed of fitting and sampling.
    seed: int = 0
    #: Synthesize the default synthetic set into ``root`` when it does not exist (``--source synthetic``).
    synthesize_missing: bool = True
    #: Scenes synthesized per layout when ``synthesize_missing`` fires (ScanNet++ layout, Replica layout).
    synthetic_counts: tuple[int, int] = (9, 3)
    #: Show progress bars (stderr).
    progress: bool = True
    transfer: TransferConfig = field(default_factory=TransferConfig)
    oracle: OracleConfig = field(default_factory=OracleConfig)
    views: ViewConfig = field(default_factory=ViewConfig)
    shards: ShardConfig = field(default_factory=ShardConfig)
    split: SplitConfig = field(default_factory=SplitConfig)


def config_dict(config) -> dict:
    """A JSON-ready dict of a (nested) config dataclass; paths as strings, tuples as lists."""

    def clean(x):
        if isinstance(x, Path):
            return str(x)
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        return x

    return clean(asdict(config))
