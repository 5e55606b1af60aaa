"""Frozen configuration of the labels of Gaussians: the nearest-point label transfer and the oracle sampler.

Kept apart from the code that uses it. ``seggaussian.pipeline.config.BuildConfig`` holds one of each; every field that
changes a stage's output takes part in that stage's cache key (``seggaussian.pipeline.scene.stage_keys``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: Margin (metres) added on every side of the labelled points' bounding box before the KD-tree query;
#: Gaussians outside the enlarged box are ignored without a query (and counted).
DEFAULT_BOX_MARGIN = 0.25
#: Default of ``TransferConfig.on_surface_tolerance`` (metres): a Gaussian lies on a surface only when it sits on the
#: mesh to within rounding (a scan's Gaussian at every vertex: distance 0 in float64 from float32 barycentrics). A
#: fitted Gaussian near a surface no view sees sits at the edge of a seen one (the floor at a box's foot, the wall
#: at a window's rim) and is seen in the images as the neighbouring surface as often as not: on 4 fitted demo rooms,
#: 3 mm moved 6.6 % of the seen Gaussians to the hidden surface's label, 826 of them seen as that label against 1,284
#: seen as the label they had; 10 um moved 8, 7 of them to the label they are seen as
#: (benchmarks/hidden_surface_fits.py). Far above float32 barycentrics' error on a triangle (below 1e-7 m per metre
#: of edge).
DEFAULT_ON_SURFACE_TOLERANCE = 1e-5


@dataclass(frozen=True)
class TransferConfig:
    """Nearest-point label transfer (``seggaussian.labels.transfer``)."""

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
    #: mesh (``seggaussian.labels.placement``): a splat in another frame (``--transform``). Chosen by measurement
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
    #: Mesh sources with views: label points that the scene's ``train`` views look at but never see (the first
    #: surface along every such view's ray is nearer by more than this, metres) give no label
    #: (``seggaussian.labels.occlusion``): the wall behind a window, the floor under a box. None keeps every
    #: point (``--keep-occluded``). Counted per scene as ``occluded_points``.
    occlusion_tolerance: float | None = 0.01
    #: With the occlusion test on: a Gaussian whose closest mesh point is this near (metres) and unseen lies on that
    #: hidden surface and keeps its label (a scan turned into splats has a Gaussian on every vertex); farther
    #: Gaussians never take a hidden surface's label. Counted per scene as ``on_hidden_surface``. The default (10 um)
    #: holds the Gaussians that sit on the mesh and no fitted one by chance (``DEFAULT_ON_SURFACE_TOLERANCE``).
    on_surface_tolerance: float = DEFAULT_ON_SURFACE_TOLERANCE


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
