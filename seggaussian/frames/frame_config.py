"""The splat's frame as the commands take it (``--transform``, ``--from-frame``), applied on reading, and the record
of what was applied (import report, build record)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seggaussian.frames.similarity import transform_gaussians
from seggaussian.frames.transform_spec import FrameTransform, resolve_transform
from seggaussian.core.gaussians import Gaussians


@dataclass(frozen=True)
class FrameConfig:
    """Where a splat file's coordinates live, relative to the scene's (mesh) frame."""

    #: Move the splat into the scene's frame: a JSON ``{"world_from_splat": 4x4}`` (or a bare 4x4 list), nerfstudio's
    #: ``dataparser_transforms.json`` (inverted), ``gsplat:COLMAP_DIR`` (gsplat simple_trainer's normalization,
    #: recomputed from that COLMAP model and inverted), ``frame:AXES``, or ``{"chain": [...]}`` of these, applied
    #: from the splat outward. Default: the splat is already in the scene's frame.
    transform: str | None = None
    #: Axes of the splat's coordinates as three letters (RDF = OpenCV/COLMAP, the default; RUB = OpenGL/three.js;
    #: LUF, RUF, ...), converted to RDF before ``--transform``.
    from_frame: str | None = None


def to_scene_frame(gaussians: Gaussians, config: FrameConfig) -> tuple[Gaussians, FrameTransform | None]:
    """(``gaussians`` moved by the transform ``config`` names, the ``FrameTransform`` or None when there is none)."""
    if config.transform is None and config.from_frame is None:
        return gaussians, None
    frame = resolve_transform(config.transform, config.from_frame)
    if frame is None:
        return gaussians, None
    return transform_gaussians(gaussians, frame.world_from_splat), frame


def frame_record(frame: FrameTransform | None) -> dict:
    """JSON-ready record of the transform applied (``{"transform": None}`` for none)."""
    if frame is None:
        return {"transform": None}
    sim = frame.world_from_splat
    return {"transform": frame.description, "world_from_splat": np.asarray(sim.matrix, float).tolist(),
            "scale": float(sim.scale), "reflection": bool(sim.is_reflection), "details": frame.details}
