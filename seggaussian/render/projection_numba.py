"""EWA projection as fused numba kernels (float64 arithmetic, parallel over Gaussians), forward and backward.

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

from seggaussian.core.constants import (
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
from seggaussian.render.parallel import GAUSSIANS_PER_CHUNK, run_parallel

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(inline="always", **_JIT)
def _unit_quat(q0, q1, q2, q3):
    n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    if n2 > QUAT_NORM_EPS * QUAT_NORM_EPS:
        inv = 1.0 / math.sqrt(n2)
        return q0 * inv, q1 * inv, q2 * inv, q3 * inv, inv, True
    return 1.0, 0.0, 0.0, 0.0, 0.0, False


@numba.njit(inline="always", **_JIT)
def _rotmat(w, x, y, z):
    """Rotation matrix of the unit quaternion (w, x, y, z) as a row-major 9-tuple."""
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


@numba.njit(inline="always", **_JIT)
def _matmul3(a, b):
    """a @ b for row-major 9-tuples, each entry summed as (a_i0 b_0j + a_i1 b_1j) + a_i2 b_2j."""
    return (a[0] * b[0] + a[1] * b[3] + a[2] * b[6], a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
            a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
            a[3] * b[0] + a[4] * b[3] + a[5] * b[6], a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
            a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[3] + a[8] * b[6], a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
            a[6] * b[2] + a[7] * b[5] + a[8] * b[8])


@numba.njit(inline="always", **_JIT)
def _robust_det(t00, t01, t02, t10, t11, t12, a0, c0):
    """det(T T^T + d I) as in ``projection.robust_det`` (Cauchy-Binet, no cancellation)."""
    m01 = t00 * t11 - t01 * t10
    m02 = t00 * t12 - t02 * t10
    m12 = t01 * t12 - t02 * t11
    return m01 * m01 + m02 * m02 + m12 * m12 + COV2D_DILATION * (a0 + c0) + COV2D_DILATION * COV2D_DILATION


@numba.njit(inline="always", **_JIT)
def _clamp_log_scale(v):
    return min(max(v, LOG_SCALE_MIN), LOG_SCALE_FLOAT32_MAX)


@numba.njit(inline="always", **_JIT)
def _f64(x):
    """An input element as float64 (exact for float32 inputs, which are read without a converted copy)."""
    return np.float64(x)


@numba.njit(parallel=True, **_JIT)
def _project_forward(means, quats, log_scales, w2c, centre, cam, width, height,
                     means2d, conics, depths, valid, pixel_box, view_dirs):
    """One fused pass per Gaussian: no temporary arrays (all 3x3 / 2x3 products are scalars in registers)."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lxn, lxp = FOV_CLAMP * cx / fx, FOV_CLAMP * (width - cx) / fx
    lyn, lyp = FOV_CLAMP * cy / fy, FOV_CLAMP * (height - cy) / fy
    w = (w2c[0, 0], w2c[0, 1], w2c[0, 2], w2c[1, 0], w2c[1, 1], w2c[1, 2], w2c[2, 0], w2c[2, 1], w2c[2, 2])
    c0_, c1_, c2_ = centre[0], centre[1], centre[2]
    for n in prange(means.shape[0]):
        rx = _f64(means[n, 0]) - c0_
        ry = _f64(means[n, 1]) - c1_
        rz = _f64(means[n, 2]) - c2_
        dist2 = rx * rx + ry * ry + rz * rz
        if dist2 > VIEW_DIR_EPS * VIEW_DIR_EPS:
            inv = 1.0 / math.sqrt(dist2)
            view_dirs[n, 0], view_dirs[n, 1], view_dirs[n, 2] = rx * inv, ry * inv, rz * inv
        else:
            view_dirs[n, 0], view_dirs[n, 1], view_dirs[n, 2] = 0.0, 0.0, 1.0
        x = w[0] * rx + w[1] * ry + w[2] * rz
        y = w[3] * rx + w[4] * ry + w[5] * rz
        z = w[6] * rx + w[7] * ry + w[8] * rz
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
        qw, qx, qy, qz, _, _ = _unit_quat(_f64(quats[n, 0]), _f64(quats[n, 1]), _f64(quats[n, 2]),
                                          _f64(quats[n, 3]))
        wr = _matmul3(w, _rotmat(qw, qx, qy, qz))  # W Rq
        s0 = math.exp(_clamp_log_scale(_f64(log_scales[n, 0])))
        s1 = math.exp(_clamp_log_scale(_f64(log_scales[n, 1])))
        s2 = math.exp(_clamp_log_scale(_f64(log_scales[n, 2])))
        m00, m01, m02 = wr[0] * s0, wr[1] * s1, wr[2] * s2  # M = W Rq S
        m10, m11, m12 = wr[3] * s0, wr[4] * s1, wr[5] * s2
        m20, m21, m22 = wr[6] * s0, wr[7] * s1, wr[8] * s2
        inv_z = 1.0 / z
        u, v = x * inv_z, y * inv_z
        uc = min(max(u, -lxn), lxp)
        vc = min(max(v, -lyn), lyp)
        j00, j02 = fx * inv_z, -fx * uc * inv_z
        j11, j12 = fy * inv_z, -fy * vc * inv_z
        # T = J M  (2 x 3); cov2d = T T^T
        t00, t01, t02 = j00 * m00 + j02 * m20, j00 * m01 + j02 * m21, j00 * m02 + j02 * m22
        t10, t11, t12 = j11 * m10 + j12 * m20, j11 * m11 + j12 * m21, j11 * m12 + j12 * m22
        a0 = t00 * t00 + t01 * t01 + t02 * t02
        b = t00 * t10 + t01 * t11 + t02 * t12
        c0 = t10 * t10 + t11 * t11 + t12 * t12
        a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
        det = _robust_det(t00, t01, t02, t10, t11, t12, a0, c0)
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
def _project_backward(means, quats, log_scales, w2c, centre, cam, width, height, valid,
                      g_means2d, g_conics, g_depths, g_dirs, d_means, d_quats, d_log_scales):
    """Chain rule of ``_project_forward``, one fused pass per Gaussian, no temporary arrays."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lxn, lxp = FOV_CLAMP * cx / fx, FOV_CLAMP * (width - cx) / fx
    lyn, lyp = FOV_CLAMP * cy / fy, FOV_CLAMP * (height - cy) / fy
    w = (w2c[0, 0], w2c[0, 1], w2c[0, 2], w2c[1, 0], w2c[1, 1], w2c[1, 2], w2c[2, 0], w2c[2, 1], w2c[2, 2])
    c0_, c1_, c2_ = centre[0], centre[1], centre[2]
    for n in prange(means.shape[0]):
        rx = _f64(means[n, 0]) - c0_
        ry = _f64(means[n, 1]) - c1_
        rz = _f64(means[n, 2]) - c2_
        d_r0 = d_r1 = d_r2 = 0.0
        dist2 = rx * rx + ry * ry + rz * rz
        if dist2 > VIEW_DIR_EPS * VIEW_DIR_EPS:  # view direction r / |r|
            inv = 1.0 / math.sqrt(dist2)
            dx_, dy_, dz_ = rx * inv, ry * inv, rz * inv
            gd0, gd1, gd2 = _f64(g_dirs[n, 0]), _f64(g_dirs[n, 1]), _f64(g_dirs[n, 2])
            dot = dx_ * gd0 + dy_ * gd1 + dz_ * gd2
            d_r0 = (gd0 - dx_ * dot) * inv
            d_r1 = (gd1 - dy_ * dot) * inv
            d_r2 = (gd2 - dz_ * dot) * inv
        d_quats[n, 0] = 0.0
        d_quats[n, 1] = 0.0
        d_quats[n, 2] = 0.0
        d_quats[n, 3] = 0.0
        d_log_scales[n, 0] = 0.0
        d_log_scales[n, 1] = 0.0
        d_log_scales[n, 2] = 0.0
        x = w[0] * rx + w[1] * ry + w[2] * rz
        y = w[3] * rx + w[4] * ry + w[5] * rz
        z = w[6] * rx + w[7] * ry + w[8] * rz
        in_depth = z > NEAR_PLANE and z < FAR_PLANE
        d_p0 = d_p1 = d_p2 = 0.0
        if in_depth:
            d_p2 += _f64(g_depths[n])
        if valid[n]:
            qw, qx, qy, qz, qinv, q_ok = _unit_quat(_f64(quats[n, 0]), _f64(quats[n, 1]), _f64(quats[n, 2]),
                                                    _f64(quats[n, 3]))
            rq = _rotmat(qw, qx, qy, qz)
            l0, l1, l2 = _f64(log_scales[n, 0]), _f64(log_scales[n, 1]), _f64(log_scales[n, 2])
            s0 = math.exp(_clamp_log_scale(l0))
            s1 = math.exp(_clamp_log_scale(l1))
            s2 = math.exp(_clamp_log_scale(l2))
            in0 = 1.0 if (l0 >= LOG_SCALE_MIN and l0 <= LOG_SCALE_FLOAT32_MAX) else 0.0
            in1 = 1.0 if (l1 >= LOG_SCALE_MIN and l1 <= LOG_SCALE_FLOAT32_MAX) else 0.0
            in2 = 1.0 if (l2 >= LOG_SCALE_MIN and l2 <= LOG_SCALE_FLOAT32_MAX) else 0.0
            wr = _matmul3(w, rq)  # W Rq
            m00, m01, m02 = wr[0] * s0, wr[1] * s1, wr[2] * s2  # M = W Rq S
            m10, m11, m12 = wr[3] * s0, wr[4] * s1, wr[5] * s2
            m20, m21, m22 = wr[6] * s0, wr[7] * s1, wr[8] * s2
            inv_z = 1.0 / z
            u, v = x * inv_z, y * inv_z
            u_free = 1.0 if (u >= -lxn and u <= lxp) else 0.0
            v_free = 1.0 if (v >= -lyn and v <= lyp) else 0.0
            uc = min(max(u, -lxn), lxp)
            vc = min(max(v, -lyn), lyp)
            j00, j02 = fx * inv_z, -fx * uc * inv_z
            j11, j12 = fy * inv_z, -fy * vc * inv_z
            # T = J M (rows t0, t1); cov2d = T T^T + dilation
            t00, t01, t02 = j00 * m00 + j02 * m20, j00 * m01 + j02 * m21, j00 * m02 + j02 * m22
            t10, t11, t12 = j11 * m10 + j12 * m20, j11 * m11 + j12 * m21, j11 * m12 + j12 * m22
            a0 = t00 * t00 + t01 * t01 + t02 * t02
            b = t00 * t10 + t01 * t11 + t02 * t12
            c0 = t10 * t10 + t11 * t11 + t12 * t12
            a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
            det = _robust_det(t00, t01, t02, t10, t11, t12, a0, c0)
            # conic = (c, -b, a) / det with det in the Cauchy-Binet form: differentiate that form directly
            # (through -Q G Q the needle-like Gaussians of huge scale lose every digit to cancellation)
            inv_det = 1.0 / det
            g0, g1, g2 = _f64(g_conics[n, 0]), _f64(g_conics[n, 1]), _f64(g_conics[n, 2])
            d_a = g2 * inv_det
            d_b = -g1 * inv_det
            d_c = g0 * inv_det
            d_det = -(g0 * c - g1 * b + g2 * a) * inv_det * inv_det
            mi01 = t00 * t11 - t01 * t10
            mi02 = t00 * t12 - t02 * t10
            mi12 = t01 * t12 - t02 * t11
            ka = 2.0 * (d_a + COV2D_DILATION * d_det)
            kc = 2.0 * (d_c + COV2D_DILATION * d_det)
            k01, k02, k12 = 2.0 * d_det * mi01, 2.0 * d_det * mi02, 2.0 * d_det * mi12
            dt00 = ka * t00 + d_b * t10 + (k01 * t11 + k02 * t12)
            dt01 = ka * t01 + d_b * t11 + (-k01 * t10 + k12 * t12)
            dt02 = ka * t02 + d_b * t12 + (-k02 * t10 - k12 * t11)
            dt10 = kc * t10 + d_b * t00 + (-k01 * t01 - k02 * t02)
            dt11 = kc * t11 + d_b * t01 + (k01 * t00 - k12 * t02)
            dt12 = kc * t12 + d_b * t02 + (k02 * t00 + k12 * t01)
            # dL/dJ = dT M^T (only the entries of J that vary are needed)
            dj00 = dt00 * m00 + dt01 * m01 + dt02 * m02
            dj02 = dt00 * m20 + dt01 * m21 + dt02 * m22
            dj11 = dt10 * m10 + dt11 * m11 + dt12 * m12
            dj12 = dt10 * m20 + dt11 * m21 + dt12 * m22
            # dL/dM = J^T dT
            dm00, dm01, dm02 = j00 * dt00, j00 * dt01, j00 * dt02
            dm10, dm11, dm12 = j11 * dt10, j11 * dt11, j11 * dt12
            dm20, dm21, dm22 = j02 * dt00 + j12 * dt10, j02 * dt01 + j12 * dt11, j02 * dt02 + j12 * dt12
            # dL/d(Rq S) = W^T dL/dM
            dn00 = w[0] * dm00 + w[3] * dm10 + w[6] * dm20
            dn01 = w[0] * dm01 + w[3] * dm11 + w[6] * dm21
            dn02 = w[0] * dm02 + w[3] * dm12 + w[6] * dm22
            dn10 = w[1] * dm00 + w[4] * dm10 + w[7] * dm20
            dn11 = w[1] * dm01 + w[4] * dm11 + w[7] * dm21
            dn12 = w[1] * dm02 + w[4] * dm12 + w[7] * dm22
            dn20 = w[2] * dm00 + w[5] * dm10 + w[8] * dm20
            dn21 = w[2] * dm01 + w[5] * dm11 + w[8] * dm21
            dn22 = w[2] * dm02 + w[5] * dm12 + w[8] * dm22
            d_log_scales[n, 0] = (dn00 * rq[0] + dn10 * rq[3] + dn20 * rq[6]) * s0 * in0
            d_log_scales[n, 1] = (dn01 * rq[1] + dn11 * rq[4] + dn21 * rq[7]) * s1 * in1
            d_log_scales[n, 2] = (dn02 * rq[2] + dn12 * rq[5] + dn22 * rq[8]) * s2 * in2
            g00, g01, g02 = dn00 * s0, dn01 * s1, dn02 * s2  # dL/dRq
            g10, g11, g12 = dn10 * s0, dn11 * s1, dn12 * s2
            g20, g21, g22 = dn20 * s0, dn21 * s1, dn22 * s2
            d_w = 2.0 * (-qz * g01 + qy * g02 + qz * g10 - qx * g12 - qy * g20 + qx * g21)
            d_x = 2.0 * (qy * g01 + qz * g02 + qy * g10 - 2.0 * qx * g11 - qw * g12 + qz * g20 + qw * g21
                         - 2.0 * qx * g22)
            d_y = 2.0 * (-2.0 * qy * g00 + qx * g01 + qw * g02 + qx * g10 + qz * g12 - qw * g20 + qz * g21
                         - 2.0 * qy * g22)
            d_zq = 2.0 * (-2.0 * qz * g00 - qw * g01 + qx * g02 + qw * g10 - 2.0 * qz * g11 + qy * g12 + qx * g20
                          + qy * g21)
            if q_ok:  # through q / |q|
                dot = qw * d_w + qx * d_x + qy * d_y + qz * d_zq
                d_quats[n, 0] = (d_w - qw * dot) * qinv
                d_quats[n, 1] = (d_x - qx * dot) * qinv
                d_quats[n, 2] = (d_y - qy * dot) * qinv
                d_quats[n, 3] = (d_zq - qz * dot) * qinv
            # Jacobian entries -> z, clamped u, v
            d_u = fx * _f64(g_means2d[n, 0])
            d_v = fy * _f64(g_means2d[n, 1])
            d_z = (-fx * dj00 + fx * uc * dj02 - fy * dj11 + fy * vc * dj12) * inv_z * inv_z
            d_u += -fx * inv_z * dj02 * u_free
            d_v += -fy * inv_z * dj12 * v_free
            d_p0 += d_u * inv_z
            d_p1 += d_v * inv_z
            d_p2 += d_z - (d_u * x + d_v * y) * inv_z * inv_z
        d_means[n, 0] = d_r0 + w[0] * d_p0 + w[3] * d_p1 + w[6] * d_p2
        d_means[n, 1] = d_r1 + w[1] * d_p0 + w[4] * d_p1 + w[7] * d_p2
        d_means[n, 2] = d_r2 + w[2] * d_p0 + w[5] * d_p1 + w[8] * d_p2


def _np64(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float64)


def _np_float(x: Tensor) -> np.ndarray:
    """Contiguous numpy view of a float32 / float64 tensor (no copy when possible); other dtypes as float64.

    The kernels read each element as float64 (exact for float32), so a float32 input needs no converted copy.
    """
    arr = x.detach().cpu().numpy()
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    return np.ascontiguousarray(arr)


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
        arrays = (_np_float(means), _np_float(quats), _np_float(log_scales))
        # every entry is written by the kernel
        means2d, conics = np.empty((n, 2)), np.empty((n, 3))
        depths, valid = np.empty(n), np.empty(n, np.bool_)
        pixel_box, view_dirs = np.empty((n, 4), np.int64), np.empty((n, 3))
        if n:
            run_parallel(_project_forward, *arrays, w2c, centre, cam, width, height, means2d, conics, depths, valid,
                         pixel_box, view_dirs, chunk=GAUSSIANS_PER_CHUNK)
        ctx.saved = (arrays, w2c, centre, cam, width, height, valid)
        ctx.dtypes = (means.dtype, quats.dtype, log_scales.dtype)
        valid_t, box_t = torch.from_numpy(valid), torch.from_numpy(pixel_box)
        ctx.mark_non_differentiable(valid_t, box_t)
        return (torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), valid_t, box_t,
                torch.from_numpy(view_dirs))

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_valid, _g_box, g_dirs):
        arrays, w2c, centre, cam, width, height, valid = ctx.saved
        n = arrays[0].shape[0]

        def grad(g, shape):
            return np.zeros(shape) if g is None else _np_float(g)

        # every entry is written by the kernel
        d_means, d_quats, d_log_scales = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3))
        if n:
            run_parallel(_project_backward, *arrays, w2c, centre, cam, width, height, valid,
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
