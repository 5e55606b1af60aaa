"""What the viewer shows: a splat file (any format, moved into the scene's frame) and/or a dataset scene with its
ground-truth labels; the splat arrays viser draws; the Gaussian under a click ray."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ovgaussian.view.cameras import file_cameras
from seggaussian import shards
from seggaussian.frames.frame_config import FrameConfig, frame_record, to_scene_frame
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians

#: A click ray picks Gaussians whose centre lies within this many of their largest standard deviations of it.
PICK_SIGMAS = 2.0
#: Gaussians less opaque than this are never picked (nearly invisible floaters).
PICK_MIN_OPACITY = 0.05
#: Without a Gaussian that close, the one of smallest angle to the ray is picked if under this (radians).
PICK_MAX_ANGLE = 0.05


class ViewScene(NamedTuple):
    """The scene of a viewer.

    Fields:
        gaussians: the Gaussians, in the scene's frame.
        source: where they came from (a path, or ``DATASET:SCENE_ID``).
        semantic: ``[N]`` ground-truth top-100 class ids (``IGNORE_LABEL`` unlabelled), or None.
        instance: ``[N]`` ground-truth instance ids, or None.
        details: JSON-ready facts (format, validation, frame transform, dataset scene).
        cameras: the scene's cameras (``shards.ViewCamera``: name, role, OpenCV ``Camera``), in the scene's frame:
            a cameras file's, else the dataset scene's views'; empty without either.
    """

    gaussians: Gaussians
    source: str
    semantic: np.ndarray | None = None
    instance: np.ndarray | None = None
    details: dict | None = None
    cameras: tuple = ()


def load_view_scene(scene: Path | None = None, dataset: Path | None = None, scene_id: str | None = None,
                    frame: FrameConfig = FrameConfig(), on_invalid: str = "error",
                    cameras: Path | None = None) -> ViewScene:
    """A splat file (``scene``, moved by ``frame``), a dataset scene (``dataset`` + ``scene_id``: its Gaussians,
    labels and view cameras), or both: the file's Gaussians with the dataset scene's labels (same count and order
    required). ``cameras``: a cameras file (``ovgaussian predict --cameras``'s format), in the scene's frame,
    replacing the dataset's."""
    if scene is None and dataset is None:
        raise ValueError("view: give a SCENE file, or --dataset DATASET --scene ID")
    if (dataset is None) != (scene_id is None):
        where = dataset if dataset is not None else scene
        raise ValueError(f"{where}: --dataset and --scene go together (the dataset folder and a scene id in it)")
    details: dict = {}
    gaussians = semantic = instance = None
    views: list = file_cameras(cameras) if cameras is not None else []
    if scene is not None:
        scene = Path(scene)
        gaussians, report, fmt = read_gaussians(scene, on_invalid=on_invalid)
        gaussians, applied = to_scene_frame(gaussians, frame)
        details.update(format=fmt, frame=frame_record(applied),
                       validation=report.to_dict())
    elif frame.transform is not None or frame.from_frame is not None:
        raise ValueError(f"{dataset}: --transform/--from-frame move a SCENE file; a dataset scene is already in "
                         "its scene's frame")
    if dataset is not None:
        dataset = Path(dataset)
        split = shards.find_split(dataset, scene_id)
        record = shards.read_scene(dataset, split, scene_id, views=False)
        details.update(dataset=str(dataset), scene_id=scene_id, split=split)
        if gaussians is None:
            gaussians = record.gaussians
        elif len(record.gaussians) != len(gaussians):
            raise ValueError(f"{scene}: {len(gaussians)} Gaussians, but dataset scene {scene_id} of {dataset} has "
                             f"{len(record.gaussians)}: its labels cannot be matched to this file")
        if cameras is None:
            views = shards.read_scene_cameras(dataset, split, scene_id)
        extras = record.gaussians.extras
        semantic = np.asarray(extras["semantic"]).astype(np.int64) if "semantic" in extras else None
        instance = np.asarray(extras["instance"]).astype(np.int64) if "instance" in extras else None
    source = str(scene) if scene is not None else f"{dataset}:{scene_id}"
    details.update(cameras=len(views), cameras_from=str(cameras) if cameras is not None else
                   ("dataset views" if views else None))
    return ViewScene(gaussians, source, semantic, instance, details, tuple(views))


class SplatArrays(NamedTuple):
    """What ``viser``'s ``add_gaussian_splats`` takes: centers ``[N, 3]``, covariances ``[N, 3, 3]``, the scene's
    DC colours ``[N, 3]`` uint8 and opacities ``[N, 1]`` float32."""

    centers: np.ndarray
    covariances: np.ndarray
    rgb: np.ndarray
    opacities: np.ndarray


def splat_arrays(gaussians: Gaussians) -> SplatArrays:
    """Splat arrays of ``gaussians`` (SH degree 0: the view-independent DC colour, clipped to [0, 1])."""
    rgb = np.clip(np.round(np.clip(gaussians.dc_colors(), 0.0, 1.0) * 255.0), 0, 255).astype(np.uint8)
    return SplatArrays(np.ascontiguousarray(gaussians.means, dtype=np.float32), gaussians.covariances(), rgb,
                       gaussians.opacities().astype(np.float32)[:, None])


def pick_gaussian(means: np.ndarray, radii: np.ndarray, opacities: np.ndarray, origin, direction) -> int | None:
    """The Gaussian a click ray hits: the nearest along the ray among those whose centre is within ``PICK_SIGMAS``
    radii of it (``radii``: ``[N]`` largest standard deviation); else the one of smallest angle to the ray, if under
    ``PICK_MAX_ANGLE``; None when nothing is in front."""
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    norm = np.linalg.norm(direction)
    if not np.isfinite(norm) or norm == 0.0 or len(means) == 0:
        return None
    direction = direction / norm
    rel = np.asarray(means, dtype=np.float64) - origin  # [N, 3]
    along = rel @ direction
    perp = np.linalg.norm(rel - along[:, None] * direction, axis=1)
    visible = (along > 0) & (np.asarray(opacities).reshape(-1) >= PICK_MIN_OPACITY)
    near = visible & (perp <= PICK_SIGMAS * np.asarray(radii, dtype=np.float64))
    if near.any():
        index = np.flatnonzero(near)
        return int(index[np.argmin(along[index])])
    if not visible.any():
        return None
    index = np.flatnonzero(visible)
    angle = np.arctan2(perp[index], along[index])
    best = int(np.argmin(angle))
    return int(index[best]) if angle[best] <= PICK_MAX_ANGLE else None
