"""Frozen configuration of the dataset build: label transfer, oracle Gaussians, views, shards, split.

Kept apart from the code that uses it. Every field that changes a stage's output takes part in that
stage's cache key (``seggaussian.pipeline.scene.stage_keys``), so changing one setting reruns only the stages downstream of it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

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
    #: Ray cluster address (None = start a local Ray).
    address: str | None = None
    #: ``auto`` fits when no trained PLY exists, ``always`` refits, ``never`` requires a PLY.
    fit: Literal["auto", "always", "never"] = "auto"
    #: ``fit`` = optimized Gaussians (or imported PLY); ``oracle`` = sampled from the labelled mesh; ``scan`` = one
    #: isotropic Gaussian per mesh vertex with its colour (a scan turned into splats, no fit).
    gaussians: Literal["fit", "oracle", "scan"] = "fit"
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
