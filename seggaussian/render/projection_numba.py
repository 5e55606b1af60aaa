"""EWA projection as fused numba kernels (float64, parallel over Gaussians), forward and backward.

Same mathematics, culling and outputs as ``projection.project_gaussians`` (the torch version, which is
the reference the tests compare against); the backward is the hand-written chain rule through
conic = inverse(J W R S S R^T W^T J^T + dilation), the clamped Jacobian, the pinhole projection and
the view direction. No fastmath: the binning derived from this projection must be reproducible.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from seggaussian.constants import (
    COV2D_DILATION,
    FAR_PLANE,
    FOV_CLAMP,
    LOG_SCALE_FLOAT32_MAX,
    NEAR_PLANE,
    QUAT_NORM_EPS,
    RADIUS_SIGMAS,
)
from seggaussian.render.projection import (
    LOG_SCALE_MIN,
    MAX_SCREEN_COORD,
    TILE_MARGIN_PX,
    VIEW_DIR_EPS,
    Projection,
    camera_centre,
)
from seggaussian.render.rasterize_numba import GAUSSIANS_PER_CHUNK, run_parallel

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(inline="always", **_JIT)
def _unit_quat(q0, q1, q2, q3):
    n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    if n2 > QUAT_NORM_EPS * QUAT_NORM_EPS:
        inv = 1.0 / math.sqrt(n2)
        return q0 * inv, q1 * inv, q2 * inv, q3 * inv, inv, True
    return 1.0, 0.0, 0.0, 0.0, 0.0, False


@numba.njit(inline="always", **_JIT)
def _rotmat(w, x, y, z, out):
    out[0, 0] = 1 - 2 * (y * y + z * z)
    out[0, 1] = 2 * (x * y - w * z)
    out[0, 2] = 2 * (x * z + w * y)
    out[1, 0] = 2 * (x * y + w * z)
    out[1, 1] = 1 - 2 * (x * x + z * z)
    out[1, 2] = 2 * (y * z - w * x)
    out[2, 0] = 2 * (x * z - w * y)
    out[2, 1] = 2 * (y * z + w * x)
    out[2, 2] = 1 - 2 * (x * x + y * y)


@numba.njit(inline="always", **_JIT)
def _robust_det(t0, t1, a0, c0):
    """det(T T^T + d I) as in ``projection.robust_det`` (Cauchy-Binet, no cancellation)."""
    m01 = t0[0] * t1[1] - t0[1] * t1[0]
    m02 = t0[0] * t1[2] - t0[2] * t1[0]
    m12 = t0[1] * t1[2] - t0[2] * t1[1]
    return m01 * m01 + m02 * m02 + m12 * m12 + COV2D_DILATION * (a0 + c0) + COV2D_DILATION * COV2D_DILATION


@numba.njit(inline="always", **_JIT)
def _clamp_log_scale(v):
    return min(max(v, LOG_SCALE_MIN), LOG_SCALE_FLOAT32_MAX)


@numba.njit(parallel=True, **_JIT)
def _project_forward(means, quats, log_scales, w2c, centre, cam, width, height,
                     means2d, conics, depths, valid, pixel_box, view_dirs):
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lxn, lxp = FOV_CLAMP * cx / fx, FOV_CLAMP * (width - cx) / fx
    lyn, lyp = FOV_CLAMP * cy / fy, FOV_CLAMP * (height - cy) / fy
    for n in prange(means.shape[0]):
        rx = means[n, 0] - centre[0]
        ry = means[n, 1] - centre[1]
        rz = means[n, 2] - centre[2]
        dist2 = rx * rx + ry * ry + rz * rz
        if dist2 > VIEW_DIR_EPS * VIEW_DIR_EPS:
            inv = 1.0 / math.sqrt(dist2)
            view_dirs[n, 0], view_dirs[n, 1], view_dirs[n, 2] = rx * inv, ry * inv, rz * inv
        else:
            view_dirs[n, 0], view_dirs[n, 1], view_dirs[n, 2] = 0.0, 0.0, 1.0
        x = w2c[0, 0] * rx + w2c[0, 1] * ry + w2c[0, 2] * rz
        y = w2c[1, 0] * rx + w2c[1, 1] * ry + w2c[1, 2] * rz
        z = w2c[2, 0] * rx + w2c[2, 1] * ry + w2c[2, 2] * rz
        means2d[n, 0] = 0.0
        means2d[n, 1] = 0.0
        conics[n, 0] = 0.0
        conics[n, 1] = 0.0
        conics[n, 2] = 0.0
        valid[n] = False
        pixel_box[n, 0] = 0
        pixel_box[n, 1] = 0
        pixel_box[n, 2] = -1
        pixel_box[n, 3] = -1
        in_depth = z > NEAR_PLANE and z < FAR_PLANE
        depths[n] = z if in_depth else 0.0
        if not in_depth:
            continue
        w, qx, qy, qz, _, _ = _unit_quat(quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3])
        rq = np.empty((3, 3))
        _rotmat(w, qx, qy, qz, rq)
        m = np.empty((3, 3))  # W Rq S
        for i in range(3):
            for j in range(3):
                m[i, j] = (w2c[i, 0] * rq[0, j] + w2c[i, 1] * rq[1, j] + w2c[i, 2] * rq[2, j]) * math.exp(
                    _clamp_log_scale(log_scales[n, j]))
        inv_z = 1.0 / z
        u, v = x * inv_z, y * inv_z
        uc = min(max(u, -lxn), lxp)
        vc = min(max(v, -lyn), lyp)
        j00, j02 = fx * inv_z, -fx * uc * inv_z
        j11, j12 = fy * inv_z, -fy * vc * inv_z
        # T = J M  (2 x 3); cov2d = T T^T
        t0 = np.empty(3)
        t1 = np.empty(3)
        for j in range(3):
            t0[j] = j00 * m[0, j] + j02 * m[2, j]
            t1[j] = j11 * m[1, j] + j12 * m[2, j]
        a0 = t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2]
        b = t0[0] * t1[0] + t0[1] * t1[1] + t0[2] * t1[2]
        c0 = t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2]
        a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
        det = _robust_det(t0, t1, a0, c0)
        mx, my = fx * u + cx, fy * v + cy
        if not (math.isfinite(det) and math.isfinite(a) and math.isfinite(c) and det > 0.0):
            continue
        if not (abs(mx) < MAX_SCREEN_COORD and abs(my) < MAX_SCREEN_COORD):
            continue
        ext_x = RADIUS_SIGMAS * math.sqrt(a) + TILE_MARGIN_PX
        ext_y = RADIUS_SIGMAS * math.sqrt(c) + TILE_MARGIN_PX
        u0 = max(min(max(np.ceil(mx - ext_x - 0.5), -1.0), width), 0.0)
        u1 = min(min(max(np.floor(mx + ext_x - 0.5), -1.0), width), width - 1.0)
        v0 = max(min(max(np.ceil(my - ext_y - 0.5), -1.0), height), 0.0)
        v1 = min(min(max(np.floor(my + ext_y - 0.5), -1.0), height), height - 1.0)
        if u0 > u1 or v0 > v1:
            continue
        valid[n] = True
        pixel_box[n, 0], pixel_box[n, 1], pixel_box[n, 2], pixel_box[n, 3] = int(u0), int(v0), int(u1), int(v1)
        means2d[n, 0], means2d[n, 1] = mx, my
        conics[n, 0], conics[n, 1], conics[n, 2] = c / det, -b / det, a / det


@numba.njit(parallel=True, **_JIT)
def _project_backward(means, quats, log_scales, w2c, centre, cam, width, height, valid, depths_out,
                      g_means2d, g_conics, g_depths, g_dirs, d_means, d_quats, d_log_scales):
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lxn, lxp = FOV_CLAMP * cx / fx, FOV_CLAMP * (width - cx) / fx
    lyn, lyp = FOV_CLAMP * cy / fy, FOV_CLAMP * (height - cy) / fy
    for n in prange(means.shape[0]):
        rx = means[n, 0] - centre[0]
        ry = means[n, 1] - centre[1]
        rz = means[n, 2] - centre[2]
        d_r = np.zeros(3)
        dist2 = rx * rx + ry * ry + rz * rz
        if dist2 > VIEW_DIR_EPS * VIEW_DIR_EPS:  # view direction r / |r|
            inv = 1.0 / math.sqrt(dist2)
            dx_, dy_, dz_ = rx * inv, ry * inv, rz * inv
            dot = dx_ * g_dirs[n, 0] + dy_ * g_dirs[n, 1] + dz_ * g_dirs[n, 2]
            d_r[0] = (g_dirs[n, 0] - dx_ * dot) * inv
            d_r[1] = (g_dirs[n, 1] - dy_ * dot) * inv
            d_r[2] = (g_dirs[n, 2] - dz_ * dot) * inv
        for j in range(4):
            d_quats[n, j] = 0.0
        for j in range(3):
            d_log_scales[n, j] = 0.0
        x = w2c[0, 0] * rx + w2c[0, 1] * ry + w2c[0, 2] * rz
        y = w2c[1, 0] * rx + w2c[1, 1] * ry + w2c[1, 2] * rz
        z = w2c[2, 0] * rx + w2c[2, 1] * ry + w2c[2, 2] * rz
        in_depth = z > NEAR_PLANE and z < FAR_PLANE
        d_p = np.zeros(3)
        if in_depth:
            d_p[2] += g_depths[n]
        if valid[n]:
            w, qx, qy, qz, qinv, q_ok = _unit_quat(quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3])
            rq = np.empty((3, 3))
            _rotmat(w, qx, qy, qz, rq)
            s = np.empty(3)
            ls_in = np.empty(3)
            for j in range(3):
                v_ = log_scales[n, j]
                s[j] = math.exp(_clamp_log_scale(v_))
                ls_in[j] = 1.0 if (v_ >= LOG_SCALE_MIN and v_ <= LOG_SCALE_FLOAT32_MAX) else 0.0
            wr = np.empty((3, 3))  # W Rq
            m = np.empty((3, 3))  # W Rq S
            for i in range(3):
                for j in range(3):
                    wr[i, j] = w2c[i, 0] * rq[0, j] + w2c[i, 1] * rq[1, j] + w2c[i, 2] * rq[2, j]
                    m[i, j] = wr[i, j] * s[j]
            inv_z = 1.0 / z
            u, v = x * inv_z, y * inv_z
            u_free = 1.0 if (u >= -lxn and u <= lxp) else 0.0
            v_free = 1.0 if (v >= -lyn and v <= lyp) else 0.0
            uc = min(max(u, -lxn), lxp)
            vc = min(max(v, -lyn), lyp)
            jac = np.zeros((2, 3))
            jac[0, 0], jac[0, 2] = fx * inv_z, -fx * uc * inv_z
            jac[1, 1], jac[1, 2] = fy * inv_z, -fy * vc * inv_z
            t0 = np.empty(3)  # T = J M (rows t0, t1); cov2d = T T^T + dilation
            t1 = np.empty(3)
            for j in range(3):
                t0[j] = jac[0, 0] * m[0, j] + jac[0, 2] * m[2, j]
                t1[j] = jac[1, 1] * m[1, j] + jac[1, 2] * m[2, j]
            a0 = t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2]
            b = t0[0] * t1[0] + t0[1] * t1[1] + t0[2] * t1[2]
            c0 = t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2]
            a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
            det = _robust_det(t0, t1, a0, c0)
            # conic = (c, -b, a) / det with det in the Cauchy-Binet form: differentiate that form directly
            # (through -Q G Q the needle-like Gaussians of huge scale lose every digit to cancellation)
            inv_det = 1.0 / det
            g0, g1, g2 = g_conics[n, 0], g_conics[n, 1], g_conics[n, 2]
            d_a = g2 * inv_det
            d_b = -g1 * inv_det
            d_c = g0 * inv_det
            d_det = -(g0 * c - g1 * b + g2 * a) * inv_det * inv_det
            m01 = t0[0] * t1[1] - t0[1] * t1[0]
            m02 = t0[0] * t1[2] - t0[2] * t1[0]
            m12 = t0[1] * t1[2] - t0[2] * t1[1]
            ka = 2.0 * (d_a + COV2D_DILATION * d_det)
            kc = 2.0 * (d_c + COV2D_DILATION * d_det)
            k01, k02, k12 = 2.0 * d_det * m01, 2.0 * d_det * m02, 2.0 * d_det * m12
            d_t = np.empty((2, 3))
            for j in range(3):
                d_t[0, j] = ka * t0[j] + d_b * t1[j]
                d_t[1, j] = kc * t1[j] + d_b * t0[j]
            d_t[0, 0] += k01 * t1[1] + k02 * t1[2]
            d_t[0, 1] += -k01 * t1[0] + k12 * t1[2]
            d_t[0, 2] += -k02 * t1[0] - k12 * t1[1]
            d_t[1, 0] += -k01 * t0[1] - k02 * t0[2]
            d_t[1, 1] += k01 * t0[0] - k12 * t0[2]
            d_t[1, 2] += k02 * t0[0] + k12 * t0[1]
            d_j = np.empty((2, 3))
            for i in range(2):
                for j in range(3):
                    d_j[i, j] = d_t[i, 0] * m[j, 0] + d_t[i, 1] * m[j, 1] + d_t[i, 2] * m[j, 2]
            d_m = np.empty((3, 3))
            for i in range(3):
                for j in range(3):
                    d_m[i, j] = jac[0, i] * d_t[0, j] + jac[1, i] * d_t[1, j]
            d_n = np.empty((3, 3))  # dL/d(Rq S) = W^T dL/dM
            for i in range(3):
                for j in range(3):
                    d_n[i, j] = w2c[0, i] * d_m[0, j] + w2c[1, i] * d_m[1, j] + w2c[2, i] * d_m[2, j]
            g_r = np.empty((3, 3))  # dL/dRq
            for j in range(3):
                d_s = 0.0
                for i in range(3):
                    g_r[i, j] = d_n[i, j] * s[j]
                    d_s += d_n[i, j] * rq[i, j]
                d_log_scales[n, j] = d_s * s[j] * ls_in[j]
            d_w = 2.0 * (-qz * g_r[0, 1] + qy * g_r[0, 2] + qz * g_r[1, 0] - qx * g_r[1, 2] - qy * g_r[2, 0]
                         + qx * g_r[2, 1])
            d_x = 2.0 * (qy * g_r[0, 1] + qz * g_r[0, 2] + qy * g_r[1, 0] - 2.0 * qx * g_r[1, 1] - w * g_r[1, 2]
                         + qz * g_r[2, 0] + w * g_r[2, 1] - 2.0 * qx * g_r[2, 2])
            d_y = 2.0 * (-2.0 * qy * g_r[0, 0] + qx * g_r[0, 1] + w * g_r[0, 2] + qx * g_r[1, 0] + qz * g_r[1, 2]
                         - w * g_r[2, 0] + qz * g_r[2, 1] - 2.0 * qy * g_r[2, 2])
            d_zq = 2.0 * (-2.0 * qz * g_r[0, 0] - w * g_r[0, 1] + qx * g_r[0, 2] + w * g_r[1, 0]
                          - 2.0 * qz * g_r[1, 1] + qy * g_r[1, 2] + qx * g_r[2, 0] + qy * g_r[2, 1])
            if q_ok:  # through q / |q|
                dot = w * d_w + qx * d_x + qy * d_y + qz * d_zq
                d_quats[n, 0] = (d_w - w * dot) * qinv
                d_quats[n, 1] = (d_x - qx * dot) * qinv
                d_quats[n, 2] = (d_y - qy * dot) * qinv
                d_quats[n, 3] = (d_zq - qz * dot) * qinv
            # Jacobian entries -> z, clamped u, v
            d_u = fx * g_means2d[n, 0]
            d_v = fy * g_means2d[n, 1]
            d_z = (-fx * d_j[0, 0] + fx * uc * d_j[0, 2] - fy * d_j[1, 1] + fy * vc * d_j[1, 2]) * inv_z * inv_z
            d_u += -fx * inv_z * d_j[0, 2] * u_free
            d_v += -fy * inv_z * d_j[1, 2] * v_free
            d_p[0] += d_u * inv_z
            d_p[1] += d_v * inv_z
            d_p[2] += d_z - (d_u * x + d_v * y) * inv_z * inv_z
        for i in range(3):
            d_means[n, i] = d_r[i] + w2c[0, i] * d_p[0] + w2c[1, i] * d_p[1] + w2c[2, i] * d_p[2]


def _np64(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float64)


def _camera_arrays(viewmat: Tensor, K: Tensor):
    w2c = _np64(viewmat[:3, :3])
    centre = camera_centre(viewmat.detach()).cpu().numpy()
    k = _np64(K)
    return w2c, centre, np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])


class _ProjectFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, viewmat, K, width, height):
        n = means.shape[0]
        w2c, centre, cam = _camera_arrays(viewmat, K)
        arrays = (_np64(means), _np64(quats), _np64(log_scales))
        means2d, conics = np.zeros((n, 2)), np.zeros((n, 3))
        depths, valid = np.zeros(n), np.zeros(n, np.bool_)
        pixel_box, view_dirs = np.zeros((n, 4), np.int64), np.zeros((n, 3))
        if n:
            run_parallel(_project_forward, *arrays, w2c, centre, cam, width, height, means2d, conics, depths, valid,
                         pixel_box, view_dirs, chunk=GAUSSIANS_PER_CHUNK)
        ctx.saved = (arrays, w2c, centre, cam, width, height, valid, depths)
        ctx.dtypes = (means.dtype, quats.dtype, log_scales.dtype)
        valid_t, box_t = torch.from_numpy(valid), torch.from_numpy(pixel_box)
        ctx.mark_non_differentiable(valid_t, box_t)
        return (torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), valid_t, box_t,
                torch.from_numpy(view_dirs))

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_valid, _g_box, g_dirs):
        arrays, w2c, centre, cam, width, height, valid, depths = ctx.saved
        n = arrays[0].shape[0]

        def grad(g, shape):
            return np.zeros(shape) if g is None else _np64(g)

        d_means, d_quats, d_log_scales = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3))
        if n:
            run_parallel(_project_backward, *arrays, w2c, centre, cam, width, height, valid, depths,
                         grad(g_means2d, (n, 2)), grad(g_conics, (n, 3)), grad(g_depths, (n,)),
                         grad(g_dirs, (n, 3)), d_means, d_quats, d_log_scales, chunk=GAUSSIANS_PER_CHUNK)
        return (torch.from_numpy(d_means).to(ctx.dtypes[0]), torch.from_numpy(d_quats).to(ctx.dtypes[1]),
                torch.from_numpy(d_log_scales).to(ctx.dtypes[2]), None, None, None, None)


def project_gaussians_fast(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
) -> Projection:
    """``projection.project_gaussians`` with numba kernels (float64 outputs, differentiable)."""
    return Projection(*_ProjectFunction.apply(means, quats, log_scales, viewmat, K, int(width), int(height)))
