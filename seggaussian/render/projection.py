"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (differentiable, pure torch).

Shared by every rasterizer backend, so culling and the 3-sigma cutoff are decided once.

The projection runs in float64 on means recentred on the camera centre: the camera-space position is
``R (mean - centre)`` rather than ``R mean + t``, so a scene far from the origin projects exactly as the
same scene moved next to the origin, and the binning that depends on it is reproducible.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from seggaussian.core.constants import (
    COV2D_DILATION,
    FAR_PLANE,
    FOV_CLAMP,
    LOG_SCALE_FLOAT32_MAX,
    NEAR_PLANE,
    QUAT_NORM_EPS,
    RADIUS_SIGMAS,
)
from seggaussian.core.rotations import quats_to_rotmats_torch

#: Log-scales are clamped below this before ``exp`` (exp(-30) ~ 1e-13 m, far below any pixel), so
#: ``-inf`` (a zero scale) gives finite values and gradients.
LOG_SCALE_MIN = -30.0
#: Projected centres farther than this from the origin of the image (pixels) are culled: such a
#: Gaussian is in front of the camera but so far off axis that float32 pixel arithmetic loses it.
MAX_SCREEN_COORD = 1e7
#: Extra pixels added around the 3-sigma box when choosing tiles, so that float32 rounding in a kernel
#: never reaches a pixel outside the tiles it was binned to.
TILE_MARGIN_PX = 1.0
#: A view direction (camera centre -> mean) shorter than this (metres) is replaced by +z.
VIEW_DIR_EPS = 1e-12


class Projection(NamedTuple):
    """Screen-space Gaussians. Entries of culled Gaussians (``valid`` False) are finite but meaningless.

    Fields:
        means2d: ``[N, 2]`` pixel coordinates of the centres (continuous; pixel centres at +0.5).
        conics: ``[N, 3]`` inverse 2D covariance ``(a, b, c)``: Mahalanobis^2 = a dx^2 + 2 b dx dy + c dy^2.
        depths: ``[N]`` camera-space z (metres).
        valid: ``[N]`` bool: in front of the near plane, before the far plane, finite, box on screen.
        pixel_box: ``[N, 4]`` int64 ``(u_min, v_min, u_max, v_max)`` inclusive pixel range that can hold the
            3-sigma ellipse (plus TILE_MARGIN_PX), clipped to the image; meaningless where not valid.
        view_dirs: ``[N, 3]`` unit direction camera centre -> mean (world frame) for SH evaluation.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    valid: Tensor
    pixel_box: Tensor
    view_dirs: Tensor


def normalize_quats(quats: Tensor) -> Tensor:  # [N, 4] -> [N, 4]
    """Unit quaternions; rows with norm <= QUAT_NORM_EPS become the identity (finite gradients)."""
    norm2 = (quats * quats).sum(-1, keepdim=True)
    ok = norm2 > QUAT_NORM_EPS**2
    safe = torch.where(ok, norm2, torch.ones_like(norm2))
    unit = quats * torch.rsqrt(safe)
    identity = torch.zeros_like(quats)
    identity[:, 0] = 1.0
    return torch.where(ok, unit, identity)


def robust_det(t0: Tensor, t1: Tensor, a0: Tensor, c0: Tensor) -> Tensor:
    """det(T T^T + d I) for T = [t0; t1] (rows [N, 3]), a0 = |t0|^2, c0 = |t1|^2, d = COV2D_DILATION.

    ``a c - b^2`` cancels catastrophically for needle-like Gaussians with huge scales; the Cauchy-Binet
    form (sum of squared 2x2 minors) + d (a0 + c0) + d^2 is a sum of non-negative terms.
    """
    m01 = t0[..., 0] * t1[..., 1] - t0[..., 1] * t1[..., 0]
    m02 = t0[..., 0] * t1[..., 2] - t0[..., 2] * t1[..., 0]
    m12 = t0[..., 1] * t1[..., 2] - t0[..., 2] * t1[..., 1]
    return m01 * m01 + m02 * m02 + m12 * m12 + COV2D_DILATION * (a0 + c0) + COV2D_DILATION**2


def camera_centre(viewmat: Tensor) -> Tensor:  # [4, 4] world-to-camera -> [3] (float64)
    r = viewmat[:3, :3].double()
    return -(r.T @ viewmat[:3, 3].double())


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
) -> Projection:
    """EWA splatting with the pinhole Jacobian (3DGS reference), in float64, differentiable.

    cov2d = J W cov3d W^T J^T + COV2D_DILATION I, with the Jacobian evaluated at the camera-space position
    whose x/z, y/z are clamped to FOV_CLAMP times the (per side) half field of view. Outputs are float64.
    """
    f64 = torch.float64
    rot_w2c = viewmat[:3, :3].detach().to(f64)
    centre = camera_centre(viewmat.detach())
    K64 = K.detach().to(f64)
    fx, fy, cx, cy = K64[0, 0], K64[1, 1], K64[0, 2], K64[1, 2]

    means_rel = means.to(f64) - centre  # recentre: exact in float64 for any realistic offset
    p_cam = means_rel @ rot_w2c.T  # [N, 3]
    x, y, z = p_cam.unbind(-1)
    in_depth = (z > NEAR_PLANE) & (z < FAR_PLANE)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))

    # 3D covariance in camera axes: (W R S)(W R S)^T
    rot = quats_to_rotmats_torch(normalize_quats(quats.to(f64)))
    scales = torch.exp(log_scales.to(f64).clamp(LOG_SCALE_MIN, LOG_SCALE_FLOAT32_MAX))
    m = rot_w2c @ rot * scales[:, None, :]  # [N, 3, 3]

    # Jacobian with the off-screen clamp
    lim_x_neg, lim_x_pos = FOV_CLAMP * cx / fx, FOV_CLAMP * (width - cx) / fx
    lim_y_neg, lim_y_pos = FOV_CLAMP * cy / fy, FOV_CLAMP * (height - cy) / fy
    tx = torch.minimum(torch.maximum(x / z_safe, -lim_x_neg), lim_x_pos) * z_safe
    ty = torch.minimum(torch.maximum(y / z_safe, -lim_y_neg), lim_y_pos) * z_safe
    zeros = torch.zeros_like(z)
    inv_z = 1.0 / z_safe
    jac = torch.stack(
        [fx * inv_z, zeros, -fx * tx * inv_z * inv_z, zeros, fy * inv_z, -fy * ty * inv_z * inv_z], -1
    ).reshape(-1, 2, 3)
    # cov2d = T T^T + dilation I with T = J W R S  [N, 2, 3]
    t = jac @ m
    t0, t1 = t[:, 0], t[:, 1]
    a0, b, c0 = (t0 * t0).sum(-1), (t0 * t1).sum(-1), (t1 * t1).sum(-1)
    a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
    det = robust_det(t0, t1, a0, c0)
    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)

    with torch.no_grad():
        finite = torch.isfinite(det) & torch.isfinite(means2d).all(-1) & torch.isfinite(a) & torch.isfinite(c)
        valid = in_depth & finite & (det > 0) & (means2d.abs() < MAX_SCREEN_COORD).all(-1)
        # 3-sigma box: the ellipse a'dx^2+... <= R^2 of the covariance spans R*sqrt(cov_xx) in x.
        safe_a = torch.where(valid, a, torch.ones_like(a))
        safe_c = torch.where(valid, c, torch.ones_like(c))
        ext_x = RADIUS_SIGMAS * torch.sqrt(safe_a) + TILE_MARGIN_PX
        ext_y = RADIUS_SIGMAS * torch.sqrt(safe_c) + TILE_MARGIN_PX
        m2 = torch.where(valid[:, None], means2d, torch.zeros_like(means2d))
        # pixel u is reached when its centre u + 0.5 lies in [mx - ext, mx + ext]
        u_min = torch.ceil(m2[:, 0] - ext_x - 0.5).clamp(-1, width)
        u_max = torch.floor(m2[:, 0] + ext_x - 0.5).clamp(-1, width)
        v_min = torch.ceil(m2[:, 1] - ext_y - 0.5).clamp(-1, height)
        v_max = torch.floor(m2[:, 1] + ext_y - 0.5).clamp(-1, height)
        u_min, v_min = u_min.clamp(min=0), v_min.clamp(min=0)
        u_max, v_max = u_max.clamp(max=width - 1), v_max.clamp(max=height - 1)
        on_screen = (u_min <= u_max) & (v_min <= v_max)
        valid = valid & on_screen
        pixel_box = torch.stack([u_min, v_min, u_max, v_max], -1).to(torch.int64)

    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1)
    conics = torch.where(valid[:, None], conics, torch.zeros_like(conics))
    means2d = torch.where(valid[:, None], means2d, torch.zeros_like(means2d))

    dist2 = (means_rel * means_rel).sum(-1, keepdim=True)
    dir_ok = dist2 > VIEW_DIR_EPS**2
    fallback = torch.zeros_like(means_rel)
    fallback[:, 2] = 1.0
    inv_dist = torch.rsqrt(torch.where(dir_ok, dist2, torch.ones_like(dist2)))
    view_dirs = torch.where(dir_ok, means_rel * inv_dist, fallback)
    return Projection(means2d, conics, torch.where(in_depth, z, zeros), valid, pixel_box, view_dirs)
