"""What a source reader returns: labelled geometry plus posed views (readers only, no fitting)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from seggaussian.core.cameras import Camera

ViewRole = Literal["train", "novel"]


@dataclass(frozen=True, eq=False)
class View:
    """One posed image of a scene.

    Fields:
        name: image name as the source lists it (e.g. ``DSC01234.JPG``, ``frame000010.jpg``).
        camera: intrinsics, world-to-camera pose (OpenCV) and size, in the scene's world frame.
        image_path: the RGB image on disk (uint8), or None when the source has none.
        role: ``train`` (used for fitting/training) or ``novel`` (held out: novel-view metrics).
        semantic_path: ground-truth semantic label image (uint16 PNG of class ids, IGNORE_LABEL
            for void) when the source has one.
        instance_path: ground-truth instance image (uint16 PNG) when the source has one.
        mask_path: anonymization mask of the image (8-bit PNG, the ScanNet++ convention: 255 = valid,
            anything else = anonymized) when the source has one; its anonymized pixels are ignore in
            the stored label maps and carry no weight in the RGB losses (``read_valid_mask``).
    """

    name: str
    camera: Camera
    image_path: Path | None
    role: ViewRole = "train"
    semantic_path: Path | None = None
    instance_path: Path | None = None
    mask_path: Path | None = None


@dataclass(frozen=True, eq=False)
class Scene:
    """A labelled scene.

    Fields:
        scene_id: identifier (ScanNet++ scene id, Replica room name, ...).
        source: ``scannetpp``, ``replica``, ``synthetic`` or ``ply``.
        points: ``[P, 3]`` float64 mesh vertices or scan points (world frame, metres).
        colors: ``[P, 3]`` uint8 RGB per point.
        semantic: ``[P]`` int32 class id (index into top100.txt) or IGNORE_LABEL.
        instance: ``[P]`` int32 instance id or IGNORE_LABEL.
        faces: ``[F, 3]`` int64 triangle indices into ``points``, or None for a point cloud.
        multilabel: ``[P, 3]`` int32 up to three class ids per point (IGNORE_LABEL padded), or None.
        views: posed images.
        root: the raw scene folder (read only).
        stats: counts the reader wants reported (frames skipped as bad, vertices masked, ...).
    """

    scene_id: str
    source: str
    points: np.ndarray
    colors: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    faces: np.ndarray | None = None
    multilabel: np.ndarray | None = None
    views: tuple[View, ...] = ()
    root: Path | None = None
    stats: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        p = self.points.shape[0] if self.points.ndim == 2 else -1
        if self.points.shape != (p, 3):
            raise ValueError(f"Scene {self.scene_id}: points has shape {self.points.shape}, expected (P, 3)")
        for name, shape in (("colors", (p, 3)), ("semantic", (p,)), ("instance", (p,))):
            if getattr(self, name).shape != shape:
                raise ValueError(f"Scene {self.scene_id}: {name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.multilabel is not None and self.multilabel.shape != (p, 3):
            raise ValueError(f"Scene {self.scene_id}: multilabel has shape {self.multilabel.shape}, expected ({p}, 3)")
        if self.faces is not None and (self.faces.ndim != 2 or self.faces.shape[1] != 3):
            raise ValueError(f"Scene {self.scene_id}: faces has shape {self.faces.shape}, expected (F, 3)")
        object.__setattr__(self, "views", tuple(self.views))

    def views_with_role(self, role: ViewRole) -> tuple[View, ...]:
        return tuple(v for v in self.views if v.role == role)
