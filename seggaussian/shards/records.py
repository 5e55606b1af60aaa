"""What one scene and one view are, as stored (``ViewRow``: encoded, to write) and as read (``SceneRecord``,
``ViewRecord``: decoded).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.core.gaussians import Gaussians


class ViewRecord(NamedTuple):
    """One view of a scene as stored.

    Fields:
        name: view (image) name.
        role: ``train`` or ``novel``.
        camera: intrinsics, world-to-camera pose (OpenCV) and size.
        rgb: ``[H, W, 3]`` uint8.
        semantic: ``[H, W]`` int32 class ids rendered from the labelled Gaussians, IGNORE_LABEL where empty.
        instance: ``[H, W]`` int32 instance ids, IGNORE_LABEL where empty.
    """

    name: str
    role: str
    camera: Camera
    rgb: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray


class ViewCamera(NamedTuple):
    """The camera of one stored view, without its images: name, role (``train`` or ``novel``) and camera
    (intrinsics, world-to-camera pose in OpenCV axes, size)."""

    name: str
    role: str
    camera: Camera


class SceneRecord(NamedTuple):
    """One scene as stored: Gaussians with ``extras`` semantic, instance, multilabel, transfer_distance."""

    scene_id: str
    source: str
    gaussians: Gaussians
    views: list


class ViewRow(NamedTuple):
    """A view ready to store: camera, encoded RGB and label maps."""

    name: str
    role: str
    camera: Camera
    rgb: bytes
    semantic: bytes
    instance: bytes
    label_coverage: float
