"""Frozen configuration of the dataset build: label transfer, oracle Gaussians, views, shards, split.

Kept apart from the code that uses it. Every field that changes a stage's output takes part in that
stage's cache key (``build_scene.stage_keys``), so changing one setting reruns only the stages downstream of it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

from seggaussian.fit_config import FitConfig

#: Margin (metres) added on every side of the labelled points' bounding box before the KD-tree query;
#: Gaussians outside the enlarged box are ignored without a query (and counted).
DEFAULT_BOX_MARGIN = 0.25


@dataclass(frozen=True)
class TransferConfig:
    """Nearest-point label transfer (``seggaussian.transfer``)."""

    #: Which points may give their label: ``all`` = every point, and a Gaussian whose nearest point is
    #: unlabelled (masked, None-mapped, out of the vocabulary) gets IGNORE_LABEL (DESIGN.md; no label
    #: spills onto unlabelled surfaces); ``labelled`` = only points whose semantic id is not IGNORE_LABEL
    #: (a Gaussian on an unlabelled surface takes the nearest labelled surface's label within the gate).
    candidates: Literal["labelled", "all"] = "all"
    #: Mesh sources: labelled points are the vertices plus samples on the triangles about this far apart
    #: (metres; ``transfer.densify_labelled_mesh``), so that a Gaussian takes the label of the nearest
    #: surface even where differently labelled surfaces are closer than the vertex spacing. 0 = vertices only.
    mesh_sample_spacing: float = 0.03
    #: Fixed distance gate in metres; None derives it from the point spacing (see the next fields).
    max_distance: float | None = None
    #: Derived gate = ``gate_factor`` x median spacing, the spacing being measured between *distinct* candidate
    #: points (exact duplicates skipped; ``transfer.median_spacing``). On the synthetic rooms (0.03 m mesh
    #: samples) the spacing is about 0.017-0.019 m, so the gate is about 0.07-0.08 m.
    gate_factor: float = 4.0
    #: Floor of the derived gate (metres): fitted Gaussians sit a few cm off dense meshes, so the gate never
    #: falls below this however dense the points are. With the spacing measured between distinct points the
    #: floor binds only below 0.0125 m spacing (e.g. ``mesh_sample_spacing`` 0.015 m). Re-swept 2026-11
    #: (``seggaussian bench --stage transfer``, benchmarks/results/stages.md): every gate_min in 0.01-0.05 and
    #: gate_factor in 2-6 gives the same label agreement (0.9577) on oracle Gaussians 1 cm off the surface;
    #: the floor stays 0.05 m because the earlier sweep, where it bound, showed 0.02 m leaving 5.8 % of
    #: off-surface Gaussians unlabelled.
    gate_min: float = 0.05
    #: Points sampled (seeded) to estimate the median spacing; the estimate costs one small query.
    spacing_samples: int = 10_000
    #: Bounding-box prefilter margin (metres). The effective margin is max(box_margin, gate), so the
    #: prefilter never changes a label the gate would have kept; its removals are counted.
    box_margin: float = DEFAULT_BOX_MARGIN
    #: Nearest-neighbour backend: ``scipy`` (cKDTree, workers=-1) or ``open3d`` (NearestNeighborSearch).
    backend: Literal["scipy", "open3d"] = "scipy"
    #: Seed of the spacing subsample.
    seed: int = 0
    #: Refuse a scene when less than this opacity-weighted share of its Gaussians lies within the gate of the
    #: mesh (``seggaussian.placement``): a splat in another frame (``--transform``). Chosen by measurement
    #: (``benchmarks/placement_thresholds.py``; margins in benchmarks/results/stages.md). 0 disables it.
    min_on_mesh_share: float = 0.4
    #: Refuse a scene when less than this share of its mesh surface has a Gaussian within the gate (a splat
    #: shrunk into the room's middle touches some surfaces, it does not cover them). The share grows with the
    #: number of Gaussians (1,500 oracle Gaussians cover 13-16 % of a synthetic room, a 10 % subsample of a fitted
    #: splat 43-64 %), so the floor is low; the other two checks catch what it lets through. 0 disables it.
    min_surface_covered_share: float = 0.05
    #: Refuse a scene whose Gaussians a local registration onto the mesh moves by more than this (metres, RMS):
    #: a splat shifted or turned by a fraction of the room, which the shares cannot see along the big planes.
    #: A negative value disables it.
    max_local_offset: float = 0.07


@dataclass(frozen=True)
class OracleConfig:
    """Gaussians sampled on the labelled mesh (``--gaussians oracle``): fast, exact geometry."""

    #: Gaussians per scene (area-weighted over triangles; over points for point clouds).
    num_gaussians: int = 40_000
    #: Sample only surfaces seen by the scene's views (first hits of rays through random pixels), as a
    #: fitted 3DGS would; False samples every triangle by area (hidden contact faces included).
    visible_only: bool = True
    #: In-plane standard deviation = ``scale_factor`` x the sample spacing (sqrt(area / N) when sampling
    #: by area; the mean distance to the 3 nearest other samples when sampling visible surfaces)
    #: by area; the pixel-sample footprint at the hit depth when sampling visible surfaces).
    scale_factor: float = 0.8
    #: Thickness (normal-axis standard deviation) as a share of the in-plane one.
    thickness_ratio: float = 0.1
    #: Opacity of every oracle Gaussian.
    opacity: float = 0.95
    #: Seed; mixed with a stable hash of the scene id.
    seed: int = 0


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
class ShardConfig:
    """Parquet layout (Hugging Face datasets conventions)."""

    #: Target uncompressed size of one row group (bytes); a row group never spans two scenes.
    row_group_bytes: int = 64 * 2**20
    #: Target compressed size of one shard file (bytes); a scene never spans two shards.
    shard_bytes: int = 512 * 2**20
    #: Parquet compression codec.
    compression: str = "zstd"
    #: Codec level (None = codec default).
    compression_level: int | None = 3


@dataclass(frozen=True)
class SplitConfig:
    """train / val / xval assignment (``seggaussian.split``)."""

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
    #: ``fit`` = optimized Gaussians (or imported PLY); ``oracle`` = sampled from the labelled mesh.
    gaussians: Literal["fit", "oracle"] = "fit"
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
