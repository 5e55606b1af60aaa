"""A plausible hand-held capture path inside a room: eye on a loop around the room centre at eye
height, looking across the room at the furniture along the opposite walls."""

from __future__ import annotations

import numpy as np

from seggaussian.core.cameras import Camera, intrinsics, look_at


def generate_camera_path(
    room_min: np.ndarray,  # [3] floor corner of the room's bounding box (z up)
    room_max: np.ndarray,  # [3] opposite ceiling corner
    num_views: int,
    K: np.ndarray,  # [3, 3]
    width: int,
    height: int,
    rng: np.random.Generator,
) -> list[Camera]:
    """``num_views`` cameras, 1.2 turns around the room, each looking at the far side."""
    room_min, room_max = np.asarray(room_min, float), np.asarray(room_max, float)
    centre = 0.5 * (room_min + room_max)
    half = 0.5 * (room_max - room_min)
    floor_z = room_min[2]
    phase = rng.uniform(0.0, 2.0 * np.pi)
    turns = 1.2
    radius_eye = rng.uniform(0.18, 0.3, size=2)
    cameras = []
    for i in range(num_views):
        angle = phase + 2.0 * np.pi * turns * i / max(num_views, 1)
        eye = np.array([
            centre[0] + radius_eye[0] * half[0] * 2 * np.cos(angle),
            centre[1] + radius_eye[1] * half[1] * 2 * np.sin(angle),
            floor_z + rng.uniform(1.3, 1.65),
        ])
        look_angle = angle + np.pi + rng.uniform(-0.5, 0.5)
        target = np.array([
            centre[0] + 0.85 * half[0] * np.cos(look_angle),
            centre[1] + 0.85 * half[1] * np.sin(look_angle),
            floor_z + rng.uniform(0.5, 1.2),
        ])
        cameras.append(Camera(K, look_at(eye, target), width, height))
    return cameras


def default_intrinsics(width: int, height: int, focal_factor: float = 0.6) -> np.ndarray:
    """Pinhole K with fx = fy = ``focal_factor * width`` and the principal point at the image centre."""
    f = focal_factor * width
    return intrinsics(f, f, 0.5 * width, 0.5 * height)
