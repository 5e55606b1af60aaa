"""Gaussians that may reach a view's image: a conservative test run before the projection, so that a large scene's
Gaussians behind or beside the camera are never projected (compiled; float64).

The projection (``projection_lanes.project_lanes``) keeps a Gaussian only if its camera depth is above
``NEAR_PLANE`` and its pixel box, the projected mean ``(mx, my)`` give or take ``ext = RADIUS_SIGMAS * sqrt(cov2d) +
TILE_MARGIN_PX`` on each axis, meets the image. The screen covariance is ``J Sigma J^T + COV2D_DILATION I`` with
``Sigma`` the camera-frame 3D covariance, whose largest eigenvalue is the square of the largest scale ``s``, and
``J``'s rows ``(f / z) (1, 0, -t)`` and ``(f / z) (0, 1, -t)``, ``|t|`` at most the Jacobian clamp's limit ``L``
(``FOV_CLAMP`` times the image's half-extent over the focal length). So ``cov2d_xx <= (fx / z)^2 (1 + Lx^2) s^2 +
COV2D_DILATION``, and likewise in y. :func:`screen_candidates` keeps every Gaussian whose mean lies within that bound
of the image (the scale taken 0.1 % larger and one more pixel, for the float rounding of either side's arithmetic):
every Gaussian the projection would keep is among them, so walking only those gives the same images, bit for bit
(tests/seggaussian/render/test_render_label_images.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from seggaussian.core.constants import COV2D_DILATION, FOV_CLAMP, LOG_SCALE_FLOAT32_MAX, NEAR_PLANE, RADIUS_SIGMAS
from seggaussian.render.projection import LOG_SCALE_MIN, TILE_MARGIN_PX

#: Relative slack on the largest scale and absolute slack in pixels of the bound (module docstring).
SCALE_SLACK, PIXEL_SLACK = 1.001, 1.0
#: Slack on the near plane (metres): a Gaussian this far in front of it is still tested by the projection.
NEAR_SLACK = 1e-9


def largest_scales(log_scales: np.ndarray) -> np.ndarray:  # [N, 3] -> [N] float64
    """Each Gaussian's largest standard deviation as the projection takes it (log-scales clamped to
    ``[LOG_SCALE_MIN, LOG_SCALE_FLOAT32_MAX]``): the view-independent part of the test, computed once per scene."""
    logs = np.asarray(log_scales, np.float64)
    if not len(logs):
        return np.zeros(0)
    return np.exp(np.clip(logs.max(axis=1), LOG_SCALE_MIN, LOG_SCALE_FLOAT32_MAX))


@numba.njit(cache=True, nogil=True)
def _candidates(means, scales, w2c, centre, fx, fy, cx, cy, lx, ly, width, height, keep):
    afx, afy = abs(fx), abs(fy)
    n = 0
    for i in range(means.shape[0]):
        rx, ry, rz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
        z = w2c[2, 0] * rx + w2c[2, 1] * ry + w2c[2, 2] * rz
        if not z > NEAR_PLANE - NEAR_SLACK:  # NaN too
            continue
        x = w2c[0, 0] * rx + w2c[0, 1] * ry + w2c[0, 2] * rz
        y = w2c[1, 0] * rx + w2c[1, 1] * ry + w2c[1, 2] * rz
        s = scales[i] * SCALE_SLACK / z
        ex = RADIUS_SIGMAS * math.sqrt(afx * afx * (1.0 + lx * lx) * s * s + COV2D_DILATION) + TILE_MARGIN_PX + PIXEL_SLACK
        ey = RADIUS_SIGMAS * math.sqrt(afy * afy * (1.0 + ly * ly) * s * s + COV2D_DILATION) + TILE_MARGIN_PX + PIXEL_SLACK
        mx, my = fx * x / z + cx, fy * y / z + cy
        if mx < -ex or mx > width + ex or my < -ey or my > height + ey:  # a NaN bound keeps the Gaussian
            continue
        keep[n] = i
        n += 1
    return n


def screen_candidates(
    means: np.ndarray,  # [N, 3]
    scales: np.ndarray,  # [N] largest_scales(log_scales)
    viewmat: np.ndarray,  # [4, 4] world -> camera (OpenCV)
    K: np.ndarray,  # [3, 3]
    width: int,
    height: int,
) -> np.ndarray:  # [M] int64, ascending
    """Indices of the Gaussians that may reach the image (module docstring), in index order."""
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    w2c = np.ascontiguousarray(viewmat[:3, :3])
    centre = -(w2c.T @ viewmat[:3, 3])
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lx = FOV_CLAMP * max(abs(cx), abs(width - cx)) / abs(fx)
    ly = FOV_CLAMP * max(abs(cy), abs(height - cy)) / abs(fy)
    keep = np.empty(len(means), np.int64)
    count = _candidates(np.ascontiguousarray(means), np.ascontiguousarray(scales, np.float64), w2c, centre, fx, fy,
                        cx, cy, lx, ly, float(width), float(height), keep)
    return keep[:count]
