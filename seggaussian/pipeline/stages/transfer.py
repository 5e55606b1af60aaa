"""transfer stage: labels of the Gaussians from the scene's labelled points -> ``gaussians.parquet``.

The algorithm (KD-tree, distance gate, statistics) is ``seggaussian.labels.transfer``; this module feeds it the
scene's points, densified along the mesh faces, less those its train views look at but never see (a wall behind a
window: ``seggaussian.labels.occlusion``) except to the Gaussians that lie on such a surface, scores the result
against the oracle truth (or the surface labels) and writes the per-scene ``gaussians`` table.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa

from seggaussian.pipeline.config import BuildConfig

from seggaussian.shards.config import ShardConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.gaussians import Gaussians
from seggaussian.labels.config import TransferConfig
from seggaussian.labels.occlusion import occluded_points, on_hidden_surface
from seggaussian.labels.placement import check_placement, measure_placement
from seggaussian.core.scene import Scene
from seggaussian.shards.files import write_parquet_atomic
from seggaussian.shards.tables import gaussians_table
from seggaussian.labels.transfer import HiddenSurfaceHits, densify_labelled_mesh, distance_gate, transfer_labels
from seggaussian.labels.scoring import label_accuracy, surface_labels
from seggaussian.sources.raycast import MeshRaycaster

#: Files the stage writes into the scene's cache folder (the views stage reads the labels back from its columns).
OUTPUTS = ("gaussians.parquet",)
#: The columns of the table that the views stage reads back (``with_labels``).
LABEL_COLUMNS = ("semantic", "instance")
#: The labels' second copy that earlier versions wrote beside the table.
FORMER_LABELS = "labels.npz"


def run_transfer(scene: Scene, gaussians: Gaussians, truth: np.ndarray | None, config: BuildConfig,
                 refuse_misplaced: bool = False, clock=None) -> tuple[Gaussians, dict]:
    """Labels of the Gaussians (transfer + per-scene statistics, placement and accuracy).

    ``refuse_misplaced``: raise ``PlacementError`` when the Gaussians do not sit on the mesh (imported splats;
    fitted and oracle Gaussians are made in the scene's frame, so theirs is only measured and reported).
    ``clock``: a ``seggaussian.pipeline.records.CpuClock`` (not imported: that module is in no stage's code digest);
    the occlusion tests' CPU seconds are counted there as ``occlusion``."""
    points, semantic, instance = scene.points, scene.semantic, scene.instance
    multilabel = scene.multilabel
    extra = 0
    if scene.faces is not None and len(scene.faces) and config.transfer.mesh_sample_spacing > 0:
        if multilabel is None:
            multilabel = np.full((len(points), 3), IGNORE_LABEL, np.int32)
            multilabel[:, 0] = semantic
        samples, (s_sem, s_inst, s_multi) = densify_labelled_mesh(
            points, scene.faces, config.transfer.mesh_sample_spacing, semantic, instance, multilabel)
        extra = len(samples)
        points = np.concatenate([points, samples])
        semantic, instance = np.concatenate([semantic, s_sem]), np.concatenate([instance, s_inst])
        multilabel = np.concatenate([multilabel, s_multi])
    with clock.measure("occlusion") if clock is not None else nullcontext():
        # one raycaster (one BVH of the mesh) for both tests, where they apply
        applies = occlusion_cameras(scene, config.transfer.occlusion_tolerance) is not None
        caster = MeshRaycaster(scene.points, scene.faces) if applies else None
        occluded = occluded_label_points(scene, points, config.transfer.occlusion_tolerance, caster)
        on_surface = hidden_surface_gaussians(scene, gaussians.means, config.transfer, caster)
    result = transfer_labels(gaussians.means, points, semantic, instance, multilabel, config.transfer,
                             hidden=occluded, on_surface=on_surface)
    # the placement is judged at the spacing-derived gate, whatever gate the user chose for the labels
    placement_gate = distance_gate(result.stats.spacing, replace(config.transfer, max_distance=None))
    placement = measure_placement(gaussians.means, gaussians.opacities(), result.distances, placement_gate,
                                  scene.points, scene.faces, scene.scene_id, config.transfer.seed)
    if refuse_misplaced:
        check_placement(placement, config.transfer.min_on_mesh_share, config.transfer.min_surface_covered_share,
                        config.transfer.max_local_offset, scene.scene_id)
    if truth is None and len(gaussians):
        faces = scene.faces
        if occluded is not None:  # score against the surfaces the views see: a face with every corner occluded is out
            vertex_occluded = occluded[: len(scene.points)]  # the label points start with the vertices, samples after
            faces = faces[~vertex_occluded[faces].all(axis=1)]
        truth = surface_labels(gaussians.means, scene.points, faces, scene.semantic)
        if on_surface is not None:  # ... except for the Gaussians on a hidden one: its closest vertex, found already
            truth[on_surface.rows] = scene.semantic[on_surface.vertex]
    accuracy = label_accuracy(result.semantic, truth) if truth is not None else {"scored": 0, "correct": 0,
                                                                                   "accuracy": None}
    inst = result.instance
    if len(inst) and int(inst[inst != IGNORE_LABEL].max(initial=0)) >= IGNORE_LABEL:
        raise ValueError(f"scene {scene.scene_id}: instance ids >= {IGNORE_LABEL} do not fit a 16-bit label map")
    labelled = gaussians.with_extras(semantic=result.semantic, instance=result.instance,
                                     multilabel=result.multilabel, transfer_distance=result.distances)
    stats = result.stats.to_dict()
    stats["mesh_samples"] = extra
    stats["occluded_points"] = int(occluded.sum()) if occluded is not None else None
    if on_surface is None:  # the occlusion test did not apply: no Gaussian was tested for a hidden surface
        stats["on_hidden_surface"] = None
    stats["placement"] = placement.to_dict()
    return labelled, {"transfer": stats, "label_accuracy": accuracy}


def occlusion_cameras(scene: Scene, tolerance: float | None) -> list | None:
    """The cameras of the scene's ``train`` views, against which label points and Gaussians are tested for surfaces
    no view sees (``seggaussian.labels.occlusion``); None where the test does not apply: ``tolerance`` None, no faces
    or no train view."""
    cameras = [view.camera for view in scene.views if view.role == "train"]
    if tolerance is None or scene.faces is None or not len(scene.faces) or not cameras:
        return None
    return cameras


def occluded_label_points(scene: Scene, points: np.ndarray, tolerance: float | None,
                          caster: MeshRaycaster | None = None) -> np.ndarray | None:
    """``[P]`` True for the label points (vertices and face samples) the scene's ``train`` views look at but never
    see; None where the test does not apply (``occlusion_cameras``). ``caster``: the scene mesh's raycaster, if built."""
    cameras = occlusion_cameras(scene, tolerance)
    return None if cameras is None else occluded_points(scene.points, scene.faces, points, cameras, tolerance, caster)


def hidden_surface_gaussians(scene: Scene, means: np.ndarray, transfer: TransferConfig,
                             caster: MeshRaycaster | None = None) -> HiddenSurfaceHits | None:
    """The Gaussians that lie on a surface the scene's ``train`` views look at but never see, with the vertex whose
    labels each keeps (``seggaussian.labels.occlusion.on_hidden_surface``); None where the test does not apply."""
    cameras = occlusion_cameras(scene, transfer.occlusion_tolerance)
    if cameras is None:
        return None
    return on_hidden_surface(means, scene.points, scene.faces, cameras, transfer.occlusion_tolerance,
                             transfer.on_surface_tolerance, caster)


def write_transfer(scene_dir: Path, scene_id: str, labelled: Gaussians, shards: ShardConfig) -> None:
    """The per-scene ``gaussians`` table (and no ``labels.npz``: one left by an earlier version goes)."""
    write_parquet_atomic(Path(scene_dir) / OUTPUTS[0], "gaussians", [gaussians_table(scene_id, labelled)], shards)
    (Path(scene_dir) / FORMER_LABELS).unlink(missing_ok=True)


def with_labels(gaussians: Gaussians, labels: pa.Table, where: Path) -> Gaussians:
    """``gaussians`` with the semantic and instance labels of the stage's ``gaussians`` table (``LABEL_COLUMNS`` of it,
    read from its per-scene file or from the shard holding its rows: the labels the views stage renders)."""
    if labels.num_rows != len(gaussians):
        raise ValueError(f"{where}: {labels.num_rows} rows for {len(gaussians)} Gaussians")
    return gaussians.with_extras(semantic=labels.column("semantic").to_numpy(),
                                 instance=labels.column("instance").to_numpy())
