"""Where the viewer's camera starts and where it can go: the scene's cameras (a dataset scene's views, or a cameras
file as ``ovgaussian predict --cameras`` reads it), and without cameras a pose inside the splat.

Conventions (data_specs/CONVENTIONS.md). A ``Camera`` is OpenCV: world-to-camera ``viewmat``, camera axes x right,
y down, z forward. viser's Python API takes cameras in the same OpenCV axes (``CameraHandle.wxyz`` is the
camera-to-world rotation, looking along its +z, up along its -y; frustums likewise) and turns them into three.js's
RUB camera (x right, y up, z back) in the browser itself. So a view's pose in the viewer is: position = the camera
centre, look direction = the third column of the camera-to-world rotation, up = minus its second column, vertical
field of view = 2 atan(H / 2 fy). The browser draws with square pixels and the principal point at the canvas centre
(:func:`browser_camera` is the ``Camera`` it shows), so a view whose principal point is off-centre is shown shifted by
that offset.

The scene's frame is the world of its source mesh, z up (Replica and ScanNet++), so "horizontal" is the xy plane:
a splat without cameras opens at its centre looking along its longest horizontal axis (:func:`centre_pose`).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from ovgaussian.predict.query import read_cameras
from seggaussian.core.cameras import Camera, intrinsics, invert_rigid
from seggaussian.core.rotations import quats_to_rotmats, rotmats_to_quats
from seggaussian.shards import ViewCamera

#: The world's up axis (the scene frame is z up).
WORLD_UP = (0.0, 0.0, 1.0)
#: Distance (metres) from a camera to the point its orbit turns around (viser orbits about ``look_at``).
LOOK_DISTANCE = 1.0
#: Vertical field of view (degrees) of the pose opened without cameras.
CENTRE_FOV_DEG = 75.0
#: Gaussian centres counted per camera when choosing the camera to open at (every k-th of a larger scene).
OPENING_SAMPLE = 20000
#: Percentiles of the horizontal coordinates taken as a bare splat's extent (floaters ignored).
EXTENT_PERCENTILES = (5.0, 95.0)


class ViewerPose(NamedTuple):
    """A camera as viser sets it: ``position``, ``look_at`` and ``up`` (``[3]`` world), vertical ``fov`` (radians)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float


def vertical_fov(camera: Camera) -> float:
    """Vertical field of view (radians) of a pinhole camera: ``2 atan(H / 2 fy)``."""
    return float(2.0 * np.arctan(0.5 * camera.height / camera.K[1, 1]))


def camera_pose(camera: Camera, look_distance: float = LOOK_DISTANCE) -> ViewerPose:
    """The viewer pose of an OpenCV camera (module docstring)."""
    c2w = camera.c2w
    position = c2w[:3, 3].copy()
    return ViewerPose(position, position + look_distance * c2w[:3, 2], -c2w[:3, 1].copy(), vertical_fov(camera))


def frustum_wxyz(camera: Camera) -> np.ndarray:
    """``[4]`` w, x, y, z quaternion of the camera-to-world rotation (viser's frustum and camera orientation)."""
    return rotmats_to_quats(camera.c2w[:3, :3][None])[0]


def browser_camera(position, wxyz, fov: float, width: int, height: int) -> Camera:
    """The ``Camera`` a browser canvas of ``width`` x ``height`` shows for a viser camera (position, OpenCV
    camera-to-world ``wxyz``, vertical ``fov``): square pixels, principal point at the canvas centre."""
    focal = 0.5 * height / np.tan(0.5 * float(fov))
    c2w = np.eye(4)
    c2w[:3, :3] = quats_to_rotmats(np.asarray(wxyz, np.float64)[None])[0]
    c2w[:3, 3] = np.asarray(position, np.float64)
    return Camera(intrinsics(focal, focal, 0.5 * width, 0.5 * height), invert_rigid(c2w), width, height)


def visible_counts(cameras: Sequence[ViewCamera], means: np.ndarray) -> np.ndarray:
    """``[V]`` how many Gaussian centres each camera sees (in front of it, inside its image)."""
    out = np.zeros(len(cameras), np.int64)
    for i, view in enumerate(cameras):
        uv, z = view.camera.project(means)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < view.camera.width) & (uv[:, 1] >= 0) \
            & (uv[:, 1] < view.camera.height)
        out[i] = int(np.count_nonzero(inside))
    return out


def opening_camera(cameras: Sequence[ViewCamera], means: np.ndarray, sample: int = OPENING_SAMPLE) -> int:
    """Index of the camera the viewer opens at: the one seeing the most Gaussian centres (the first on a tie),
    counted on at most ``sample`` of them (every k-th)."""
    if not cameras:
        raise ValueError("opening_camera: no cameras")
    means = np.asarray(means, np.float64)
    step = max(1, -(-len(means) // max(1, sample)))
    return int(np.argmax(visible_counts(cameras, means[::step])))


def centre_pose(means: np.ndarray, look_distance: float = LOOK_DISTANCE,
                fov_deg: float = CENTRE_FOV_DEG) -> ViewerPose:
    """The pose of a splat without cameras: at the median of its centres, level, looking along the principal axis
    of its horizontal (xy) spread, towards the side that reaches further (the 95th percentile of the centres along
    that axis against the 5th)."""
    means = np.asarray(means, np.float64)
    if len(means) == 0:
        position = np.zeros(3)
        return ViewerPose(position, position + look_distance * np.array([1.0, 0.0, 0.0]), np.array(WORLD_UP),
                          float(np.radians(fov_deg)))
    centre = np.median(means, axis=0)
    xy = means[:, :2] - centre[:2]
    if len(xy) >= 2:
        values, vectors = np.linalg.eigh(np.cov(xy.T))
        axis = vectors[:, int(np.argmax(values))]
    else:
        axis = np.array([1.0, 0.0])
    along = xy @ axis
    low, high = np.percentile(along, EXTENT_PERCENTILES)
    if -low > high:  # look to the side that reaches further
        axis = -axis
    direction = np.array([axis[0], axis[1], 0.0]) / max(float(np.linalg.norm(axis)), 1e-12)
    return ViewerPose(centre, centre + look_distance * direction, np.array(WORLD_UP), float(np.radians(fov_deg)))


def file_cameras(path: Path) -> list[ViewCamera]:
    """The cameras of a JSON file in ``ovgaussian predict --cameras``'s format (``predict.query.read_cameras``)."""
    return [ViewCamera(name, "file", camera) for name, camera in read_cameras(Path(path))]
