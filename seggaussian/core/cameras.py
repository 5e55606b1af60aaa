"""Pinhole cameras in the OpenCV convention (x right, y down, z forward).

``viewmat`` is the 4x4 world-to-camera transform; ``K`` the 3x3 intrinsic matrix. Pixel centres sit at
``+0.5`` (pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)``; its centre is ``(u + 0.5, v + 0.5)``), as in
the 3DGS reference rasterizer and COLMAP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Camera:
    """One pinhole view.

    Fields:
        K: ``[3, 3]`` float64 intrinsics (fx, fy on the diagonal; cx, cy in the last column).
        viewmat: ``[4, 4]`` float64 world-to-camera transform (OpenCV axes).
        width, height: image size in pixels.
    """

    K: np.ndarray
    viewmat: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        k = np.asarray(self.K, dtype=np.float64)
        v = np.asarray(self.viewmat, dtype=np.float64)
        if k.shape != (3, 3) or v.shape != (4, 4):
            raise ValueError(f"Camera: K must be 3x3 and viewmat 4x4, got {k.shape} and {v.shape}")
        if not (np.isfinite(k).all() and np.isfinite(v).all()):
            raise ValueError("Camera: K or viewmat holds NaN/Inf")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera: image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "viewmat", v)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_c2w(cls, K: np.ndarray, c2w: np.ndarray, width: int, height: int) -> "Camera":
        """From a camera-to-world pose (OpenCV axes)."""
        return cls(K, invert_rigid(np.asarray(c2w, dtype=np.float64)), width, height)

    @property
    def c2w(self) -> np.ndarray:
        """``[4, 4]`` camera-to-world pose."""
        return invert_rigid(self.viewmat)

    @property
    def center(self) -> np.ndarray:
        """``[3]`` camera centre in world coordinates."""
        return self.c2w[:3, 3]

    def scaled(self, factor: float) -> "Camera":
        """The same view with the image resized by ``factor`` (pixel-centre convention kept)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        k = self.K.copy()
        k[0] *= sx
        k[1] *= sy
        return Camera(k, self.viewmat, w, h)

    def translated(self, offset: np.ndarray) -> "Camera":
        """The same view of a world shifted by ``offset`` (x' = x + offset)."""
        t = np.eye(4)
        t[:3, 3] = -np.asarray(offset, dtype=np.float64)
        return Camera(self.K, self.viewmat @ t, self.width, self.height)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points ``[P, 3]`` -> (pixel coordinates ``[P, 2]`` (continuous), camera depth ``[P]``)."""
        p = np.asarray(points, dtype=np.float64) @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p @ self.K.T)[:, :2] / z[:, None]
        return uv, z


def invert_rigid(m: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (rotation + translation)."""
    out = np.eye(4)
    r = m[:3, :3]
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ m[:3, 3]
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera ``viewmat`` (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return invert_rigid(c2w)


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
