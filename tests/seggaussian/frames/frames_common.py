"""Shared helpers of the seggaussian.frames tests (no tests here): random rotations and Gaussians, a small room
seen by inward-looking cameras, and COLMAP text / binary writers."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from seggaussian.core.cameras import look_at
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.rotations import rotmats_to_quats


def axis_rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues: the rotation by ``degrees`` about ``axis``."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A proper rotation (det +1), uniform enough for tests (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_gaussians(n: int, degree: int, seed: int, spread: float = 0.6) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians.from_arrays(
        rng.normal(size=(n, 3)) * spread,
        rng.normal(size=(n, 4)),
        rng.normal(size=(n, 3)) * 0.4 - 2.0,
        rng.normal(size=n) * 1.5 + 0.5,
        rng.normal(size=(n, (degree + 1) ** 2, 3)) * 0.4,
        {"semantic": np.arange(n, dtype=np.int32)},
    )


def room_scene(seed: int, num_cameras: int = 12, num_points: int = 400):
    """(camera-to-world ``[C, 4, 4]`` OpenCV, points ``[P, 3]``) of a room 6 x 4 x 2.5 (z up) off the origin:
    floor-heavy points, cameras on a ring looking at the room's middle from eye height."""
    rng = np.random.default_rng(seed)
    centre = np.array([3.0, -1.0, 0.5])
    floor = np.column_stack([rng.uniform(-3, 3, num_points // 2), rng.uniform(-2, 2, num_points // 2),
                             np.zeros(num_points // 2)])
    walls = np.column_stack([rng.choice([-3.0, 3.0], num_points - num_points // 2),
                             rng.uniform(-2, 2, num_points - num_points // 2),
                             rng.uniform(0, 2.5, num_points - num_points // 2)])
    points = np.concatenate([floor, walls]) + centre + rng.normal(scale=0.01, size=(num_points, 3))
    c2w = []
    for k in range(num_cameras):
        angle = 2 * np.pi * k / num_cameras + rng.uniform(-0.1, 0.1)
        eye = centre + np.array([2.0 * np.cos(angle), 1.3 * np.sin(angle), 1.5 + rng.uniform(-0.2, 0.2)])
        target = centre + np.array([0.0, 0.0, 0.8]) + rng.normal(scale=0.2, size=3)
        c2w.append(np.linalg.inv(look_at(eye, target, up=(0.0, 0.0, 1.0))))
    return np.array(c2w), points


def _colmap_qt(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w2c = np.linalg.inv(c2w)
    q = rotmats_to_quats(w2c[None, :3, :3])[0]
    return (q if q[0] >= 0 else -q), w2c[:3, 3]


def write_colmap_text(folder: Path, c2w: np.ndarray, points: np.ndarray, names: list[str] | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"IMG_{i:04d}.JPG" for i in range(len(c2w))]
    (folder / "cameras.txt").write_text("# Camera list\n1 PINHOLE 64 48 50 50 32 24\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    for i, (pose, name) in enumerate(zip(c2w, names)):
        q, t = _colmap_qt(pose)
        lines.append(" ".join([str(i + 1), *(repr(float(x)) for x in (*q, *t)), "1", name]))
        lines.append("10.5 11.5 1 12.0 13.0 -1" if i % 2 else "")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    rows = ["# 3D point list with one line of data per point:"]
    for i, p in enumerate(points):
        rows.append(" ".join([str(i + 1), *(repr(float(x)) for x in p), "128 64 32 0.5", "1 0 2 3"]))
    (folder / "points3D.txt").write_text("\n".join(rows) + "\n")
    return folder


def write_colmap_binary(folder: Path, c2w: np.ndarray, points: np.ndarray, names: list[str] | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"IMG_{i:04d}.JPG" for i in range(len(c2w))]
    cameras = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, 64, 48) + struct.pack("<4d", 50, 50, 32, 24)
    (folder / "cameras.bin").write_bytes(cameras)
    data = struct.pack("<Q", len(c2w))
    for i, (pose, name) in enumerate(zip(c2w, names)):
        q, t = _colmap_qt(pose)
        data += struct.pack("<i4d3di", i + 1, *q, *t, 1) + name.encode() + b"\x00"
        num_points2d = i % 3
        data += struct.pack("<Q", num_points2d)
        data += b"".join(struct.pack("<ddq", 1.0, 2.0, -1) for _ in range(num_points2d))
    (folder / "images.bin").write_bytes(data)
    data = struct.pack("<Q", len(points))
    for i, p in enumerate(points):
        track = i % 3
        data += struct.pack("<Q3d3Bd", i + 1, *p, 128, 64, 32, 0.5) + struct.pack("<Q", track)
        data += b"".join(struct.pack("<ii", 1, j) for j in range(track))
    (folder / "points3D.bin").write_bytes(data)
    return folder
