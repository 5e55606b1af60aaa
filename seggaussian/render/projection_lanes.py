"""The EWA projection's per-block SIMD kernels (float64): one block of ``LANE_BLOCK`` Gaussians, staged as columns.

``projection_numba`` runs these over the blocks in parallel and wraps them in an autograd Function. A block's
inputs are copied into float64 columns of one scratch array; ``project_lanes`` (forward) and
``project_backward_lanes`` (the hand-written chain rule through conic = inverse(J W R S S R^T W^T J^T + dilation),
the clamped Jacobian, the pinhole projection and the view direction) then loop over the block with no branch and no
library call (culling by masks and selects, ``exp`` as a polynomial), which LLVM runs four Gaussians to an AVX2
instruction. Row-major ``[N, 3]`` inputs read in place do not vectorize (numba's 2D indexing hides the constant row
stride from LLVM). No fastmath: the binning derived from the projection must be reproducible, and a SIMD lane
computes the same bits as the scalar loop.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from seggaussian.core.constants import (
    COV2D_DILATION,
    FAR_PLANE,
    FOV_CLAMP,
    LOG_SCALE_FLOAT32_MAX,
    NEAR_PLANE,
    QUAT_NORM_EPS,
    RADIUS_SIGMAS,
)
from seggaussian.render.projection import LOG_SCALE_MIN, MAX_SCREEN_COORD, TILE_MARGIN_PX, VIEW_DIR_EPS

_JIT = dict(cache=True, nogil=True, error_model="numpy")


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


#: exp(x) below: Taylor's polynomial of degree _EXP_DEGREE at x / 2^_EXP_SQUARINGS, squared _EXP_SQUARINGS times.
_EXP_SQUARINGS = 8
_EXP_SHRINK = 1.0 / 2.0**_EXP_SQUARINGS
_EXP_DEGREE = 12
_EXP_TAYLOR = tuple(1.0 / math.factorial(k) for k in range(_EXP_DEGREE + 1))


@numba.njit(inline="always", **_JIT)
def _exp_scale(x):
    """exp(x) for x in [LOG_SCALE_MIN, LOG_SCALE_FLOAT32_MAX] (clamped log scales) without a library call, so that
    loops calling it vectorize: with y = x / 256 in [-0.12, 0.35], the degree-12 Taylor polynomial of exp(y)
    (truncation below 2e-16 relative), then squared 8 times. Relative error below 1e-13 (the tests hold it to
    ``math.exp``); plain IEEE arithmetic in a fixed order, so every build gives the same bits."""
    y = x * _EXP_SHRINK
    p = _EXP_TAYLOR[_EXP_DEGREE]
    for k in range(_EXP_DEGREE - 1, -1, -1):  # Horner; a constant trip count, unrolled by LLVM
        p = p * y + _EXP_TAYLOR[k]
    for _ in range(_EXP_SQUARINGS):
        p = p * p
    return p


@numba.njit(inline="always", **_JIT)
def _select(condition, a, b):
    """``a if condition else b`` as one select instruction (both sides are computed: no branch to block SIMD)."""
    return a if condition else b


#: Gaussians per block of the kernels: a block's inputs and outputs are staged as float64 columns of one scratch
#: array (24 columns of this length forward, 30 backward: 12-15 KB, within a core's L1 cache). At 1M Gaussians,
#: kernel alone, forward / backward ms: 64 -> 21 / 28-31, 256 -> 24-25 / 30, 1,024 -> 39 / 50 (scratch in L2).
LANE_BLOCK = 64
_LB = np.uint64(LANE_BLOCK)
# scratch columns: inputs (relative mean, quaternion, log scales), then outputs
_RX, _RY, _RZ, _Q0, _Q1, _Q2, _Q3, _L0, _L1, _L2 = (np.uint64(k) for k in range(10))
_VD0, _VD1, _VD2, _DEPTH, _MX, _MY, _CA, _CB, _CC, _OK, _U0, _V0, _U1, _V1 = (np.uint64(k) for k in range(10, 24))
LANE_FIELDS = 24


@numba.njit(inline="always", **_JIT)
def _unit_quat(q0, q1, q2, q3):
    """``(w, x, y, z, 1 / |q|, ok)``: ``q / |q|``, or the identity rotation where ``|q|`` is below QUAT_NORM_EPS."""
    q_norm2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    ok = q_norm2 > QUAT_NORM_EPS * QUAT_NORM_EPS
    inv = 1.0 / math.sqrt(_select(ok, q_norm2, 1.0))
    return (_select(ok, q0 * inv, 1.0), _select(ok, q1 * inv, 0.0), _select(ok, q2 * inv, 0.0),
            _select(ok, q3 * inv, 0.0), inv, ok)


@numba.njit(inline="always", **_JIT)
def _screen_covariance(w, rq, s0, s1, s2, x, y, inv_z, fx, fy, lxn, lxp, lyn, lyp):
    """The EWA chain of one Gaussian: ``M = W Rq S`` (row-major 9-tuple), the Jacobian entries ``(j00, j02, j11,
    j12)`` at the clamped ``(uc, vc)``, ``T = J M`` (6-tuple) and ``cov2d - dilation = (a0, b, c0)``; also the
    unclamped ``(u, v)``."""
    wr = _matmul3(w, rq)  # W Rq
    m = (wr[0] * s0, wr[1] * s1, wr[2] * s2, wr[3] * s0, wr[4] * s1, wr[5] * s2, wr[6] * s0, wr[7] * s1, wr[8] * s2)
    u, v = x * inv_z, y * inv_z
    uc = min(max(u, -lxn), lxp)
    vc = min(max(v, -lyn), lyp)
    j00, j02 = fx * inv_z, -fx * uc * inv_z
    j11, j12 = fy * inv_z, -fy * vc * inv_z
    t = (j00 * m[0] + j02 * m[6], j00 * m[1] + j02 * m[7], j00 * m[2] + j02 * m[8],
         j11 * m[3] + j12 * m[6], j11 * m[4] + j12 * m[7], j11 * m[5] + j12 * m[8])
    a0 = t[0] * t[0] + t[1] * t[1] + t[2] * t[2]
    b = t[0] * t[3] + t[1] * t[4] + t[2] * t[5]
    c0 = t[3] * t[3] + t[4] * t[4] + t[5] * t[5]
    return m, (j00, j02, j11, j12), (uc, vc), (u, v), t, (a0, b, c0)


@numba.njit(inline="always", **_JIT)
def new_block(block, fields, total):
    """``(lane, lo, count)`` of block ``block`` of ``total`` rows: a float64 scratch array of ``fields`` columns of
    LANE_BLOCK, the first row ``lo`` and the rows ``count`` (uint64). The last block's unused lanes hold zeros, so
    they compute on zeros."""
    lane = np.empty(fields * LANE_BLOCK, np.float64)
    lo = np.uint64(block * LANE_BLOCK)
    count = np.uint64(min(total - block * LANE_BLOCK, LANE_BLOCK))
    if count < _LB:
        lane[:] = 0.0
    return lane, lo, count


@numba.njit(inline="always", **_JIT)
def open_block(block, fields, means, quats, log_scales, centre):
    """``new_block`` whose columns ``_RX.._L2`` hold rows ``lo .. lo + count`` of the inputs as float64, means relative
    to the camera centre."""
    lane, lo, count = new_block(block, fields, means.shape[0])
    c0_, c1_, c2_ = centre[0], centre[1], centre[2]
    for i in range(count):
        n = lo + i
        lane[_RX * _LB + i] = _f64(means[n, 0]) - c0_
        lane[_RY * _LB + i] = _f64(means[n, 1]) - c1_
        lane[_RZ * _LB + i] = _f64(means[n, 2]) - c2_
        lane[_Q0 * _LB + i] = _f64(quats[n, 0])
        lane[_Q1 * _LB + i] = _f64(quats[n, 1])
        lane[_Q2 * _LB + i] = _f64(quats[n, 2])
        lane[_Q3 * _LB + i] = _f64(quats[n, 3])
        lane[_L0 * _LB + i] = _f64(log_scales[n, 0])
        lane[_L1 * _LB + i] = _f64(log_scales[n, 1])
        lane[_L2 * _LB + i] = _f64(log_scales[n, 2])
    return lane, lo, count


@numba.njit(**_JIT)
def project_lanes(lane, params):
    """The forward projection of one block, column-wise: reads the input columns of ``lane``
    (``[LANE_FIELDS * LANE_BLOCK]`` float64, column ``k`` at ``k * LANE_BLOCK``), writes its output columns.

    The loop has a constant trip count, no branch and no library call (culling is a mask, outputs go through
    selects, exp is ``_exp_scale``), and the columns lie at constant distances of at least the trip count, so LLVM
    runs it on SIMD lanes with no run-time overlap check. The arithmetic is the scalar order written here
    (no fast-math): a lane and the scalar loop give the same bits."""
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    lxn, lxp, lyn, lyp = params[4], params[5], params[6], params[7]
    w = (params[8], params[9], params[10], params[11], params[12], params[13], params[14], params[15], params[16])
    w_max, h_max = params[17], params[18]
    for i in range(_LB):
        rx, ry, rz = lane[_RX * _LB + i], lane[_RY * _LB + i], lane[_RZ * _LB + i]
        dist2 = rx * rx + ry * ry + rz * rz
        dir_ok = dist2 > VIEW_DIR_EPS * VIEW_DIR_EPS
        inv_r = 1.0 / math.sqrt(_select(dir_ok, dist2, 1.0))
        lane[_VD0 * _LB + i] = _select(dir_ok, rx * inv_r, 0.0)
        lane[_VD1 * _LB + i] = _select(dir_ok, ry * inv_r, 0.0)
        lane[_VD2 * _LB + i] = _select(dir_ok, rz * inv_r, 1.0)
        x = w[0] * rx + w[1] * ry + w[2] * rz
        y = w[3] * rx + w[4] * ry + w[5] * rz
        z = w[6] * rx + w[7] * ry + w[8] * rz
        in_depth = (z > NEAR_PLANE) & (z < FAR_PLANE)
        lane[_DEPTH * _LB + i] = _select(in_depth, z, 0.0)
        qw, qx, qy, qz, _, _ = _unit_quat(lane[_Q0 * _LB + i], lane[_Q1 * _LB + i], lane[_Q2 * _LB + i],
                                          lane[_Q3 * _LB + i])
        s0 = _exp_scale(_clamp_log_scale(lane[_L0 * _LB + i]))
        s1 = _exp_scale(_clamp_log_scale(lane[_L1 * _LB + i]))
        s2 = _exp_scale(_clamp_log_scale(lane[_L2 * _LB + i]))
        _, _, _, (u, v), t, (a0, b, c0) = _screen_covariance(
            w, _rotmat(qw, qx, qy, qz), s0, s1, s2, x, y, 1.0 / _select(in_depth, z, 1.0), fx, fy, lxn, lxp, lyn, lyp)
        a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
        det = _robust_det(t[0], t[1], t[2], t[3], t[4], t[5], a0, c0)
        mx, my = fx * u + cx, fy * v + cy
        ok = (in_depth & math.isfinite(det) & math.isfinite(a) & math.isfinite(c) & (det > 0.0)
              & (abs(mx) < MAX_SCREEN_COORD) & (abs(my) < MAX_SCREEN_COORD))
        ext_x = RADIUS_SIGMAS * math.sqrt(_select(ok, a, 1.0)) + TILE_MARGIN_PX
        ext_y = RADIUS_SIGMAS * math.sqrt(_select(ok, c, 1.0)) + TILE_MARGIN_PX
        mxs, mys = _select(ok, mx, 0.0), _select(ok, my, 0.0)
        u0 = max(min(max(np.ceil(mxs - ext_x - 0.5), -1.0), w_max), 0.0)
        u1 = min(min(max(np.floor(mxs + ext_x - 0.5), -1.0), w_max), w_max - 1.0)
        v0 = max(min(max(np.ceil(mys - ext_y - 0.5), -1.0), h_max), 0.0)
        v1 = min(min(max(np.floor(mys + ext_y - 0.5), -1.0), h_max), h_max - 1.0)
        ok = ok & (u0 <= u1) & (v0 <= v1)
        lane[_OK * _LB + i] = _select(ok, 1.0, 0.0)
        lane[_U0 * _LB + i] = _select(ok, u0, 0.0)
        lane[_V0 * _LB + i] = _select(ok, v0, 0.0)
        lane[_U1 * _LB + i] = _select(ok, u1, -1.0)
        lane[_V1 * _LB + i] = _select(ok, v1, -1.0)
        lane[_MX * _LB + i] = _select(ok, mx, 0.0)
        lane[_MY * _LB + i] = _select(ok, my, 0.0)
        det_safe = _select(ok, det, 1.0)
        lane[_CA * _LB + i] = _select(ok, c / det_safe, 0.0)
        lane[_CB * _LB + i] = _select(ok, -b / det_safe, 0.0)
        lane[_CC * _LB + i] = _select(ok, a / det_safe, 0.0)


def forward_params(w2c: np.ndarray, cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """``[19]`` float64 constants of :func:`project_lanes`: fx, fy, cx, cy, the Jacobian clamp's four limits,
    the world-to-camera rotation (row-major), the image width and height."""
    fx, fy, cx, cy = (float(v) for v in cam)
    limits = [FOV_CLAMP * cx / fx, FOV_CLAMP * (width - cx) / fx, FOV_CLAMP * cy / fy, FOV_CLAMP * (height - cy) / fy]
    return np.array([fx, fy, cx, cy, *limits, *w2c.reshape(-1), float(width), float(height)], np.float64)


# backward scratch columns: the forward's inputs (_RX.._L2), valid and the output gradients, then input gradients
_BOK, _GM0, _GM1, _GC0, _GC1, _GC2, _GZ, _GD0, _GD1, _GD2 = (np.uint64(k) for k in range(10, 20))
_DM0, _DM1, _DM2, _DQ0, _DQ1, _DQ2, _DQ3, _DL0, _DL1, _DL2 = (np.uint64(k) for k in range(20, 30))
BACKWARD_FIELDS = 30


@numba.njit(**_JIT)
def project_backward_lanes(lane, params):
    """Chain rule of :func:`project_lanes` for one block, column-wise, on SIMD lanes as the forward (no branch:
    a culled Gaussian's terms are computed on safe stand-ins and dropped by selects, so no NaN leaks in)."""
    fx, fy = params[0], params[1]
    lxn, lxp, lyn, lyp = params[4], params[5], params[6], params[7]
    w = (params[8], params[9], params[10], params[11], params[12], params[13], params[14], params[15], params[16])
    for i in range(_LB):
        rx, ry, rz = lane[_RX * _LB + i], lane[_RY * _LB + i], lane[_RZ * _LB + i]
        ok = lane[_BOK * _LB + i] != 0.0
        dist2 = rx * rx + ry * ry + rz * rz
        dir_ok = dist2 > VIEW_DIR_EPS * VIEW_DIR_EPS  # view direction r / |r|
        inv = 1.0 / math.sqrt(_select(dir_ok, dist2, 1.0))
        dx_, dy_, dz_ = rx * inv, ry * inv, rz * inv
        gd0, gd1, gd2 = lane[_GD0 * _LB + i], lane[_GD1 * _LB + i], lane[_GD2 * _LB + i]
        dot = dx_ * gd0 + dy_ * gd1 + dz_ * gd2
        d_r0 = _select(dir_ok, (gd0 - dx_ * dot) * inv, 0.0)
        d_r1 = _select(dir_ok, (gd1 - dy_ * dot) * inv, 0.0)
        d_r2 = _select(dir_ok, (gd2 - dz_ * dot) * inv, 0.0)
        x = w[0] * rx + w[1] * ry + w[2] * rz
        y = w[3] * rx + w[4] * ry + w[5] * rz
        z = w[6] * rx + w[7] * ry + w[8] * rz
        in_depth = (z > NEAR_PLANE) & (z < FAR_PLANE)
        qw, qx, qy, qz, qinv, q_ok = _unit_quat(lane[_Q0 * _LB + i], lane[_Q1 * _LB + i], lane[_Q2 * _LB + i],
                                                lane[_Q3 * _LB + i])
        rq = _rotmat(qw, qx, qy, qz)
        l0, l1, l2 = lane[_L0 * _LB + i], lane[_L1 * _LB + i], lane[_L2 * _LB + i]
        s0 = _exp_scale(_clamp_log_scale(l0))
        s1 = _exp_scale(_clamp_log_scale(l1))
        s2 = _exp_scale(_clamp_log_scale(l2))
        in0 = (l0 >= LOG_SCALE_MIN) & (l0 <= LOG_SCALE_FLOAT32_MAX)
        in1 = (l1 >= LOG_SCALE_MIN) & (l1 <= LOG_SCALE_FLOAT32_MAX)
        in2 = (l2 >= LOG_SCALE_MIN) & (l2 <= LOG_SCALE_FLOAT32_MAX)
        inv_z = 1.0 / _select(ok, z, 1.0)  # a valid Gaussian is in depth
        m, (j00, j02, j11, j12), (uc, vc), (u, v), t, (a0, b, c0) = _screen_covariance(
            w, rq, s0, s1, s2, x, y, inv_z, fx, fy, lxn, lxp, lyn, lyp)
        m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
        t00, t01, t02, t10, t11, t12 = t
        u_free = 1.0 if (u >= -lxn) & (u <= lxp) else 0.0
        v_free = 1.0 if (v >= -lyn) & (v <= lyp) else 0.0
        a, c = a0 + COV2D_DILATION, c0 + COV2D_DILATION
        det = _robust_det(t00, t01, t02, t10, t11, t12, a0, c0)
        # conic = (c, -b, a) / det with det in the Cauchy-Binet form: differentiate that form directly
        # (through -Q G Q the needle-like Gaussians of huge scale lose every digit to cancellation)
        inv_det = 1.0 / _select(ok, det, 1.0)
        g0, g1, g2 = lane[_GC0 * _LB + i], lane[_GC1 * _LB + i], lane[_GC2 * _LB + i]
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
        lane[_DL0 * _LB + i] = _select(ok & in0, (dn00 * rq[0] + dn10 * rq[3] + dn20 * rq[6]) * s0, 0.0)
        lane[_DL1 * _LB + i] = _select(ok & in1, (dn01 * rq[1] + dn11 * rq[4] + dn21 * rq[7]) * s1, 0.0)
        lane[_DL2 * _LB + i] = _select(ok & in2, (dn02 * rq[2] + dn12 * rq[5] + dn22 * rq[8]) * s2, 0.0)
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
        q_grad = ok & q_ok  # through q / |q|
        dot = qw * d_w + qx * d_x + qy * d_y + qz * d_zq
        lane[_DQ0 * _LB + i] = _select(q_grad, (d_w - qw * dot) * qinv, 0.0)
        lane[_DQ1 * _LB + i] = _select(q_grad, (d_x - qx * dot) * qinv, 0.0)
        lane[_DQ2 * _LB + i] = _select(q_grad, (d_y - qy * dot) * qinv, 0.0)
        lane[_DQ3 * _LB + i] = _select(q_grad, (d_zq - qz * dot) * qinv, 0.0)
        # Jacobian entries -> z, clamped u, v
        d_u = fx * lane[_GM0 * _LB + i]
        d_v = fy * lane[_GM1 * _LB + i]
        d_z = (-fx * dj00 + fx * uc * dj02 - fy * dj11 + fy * vc * dj12) * inv_z * inv_z
        d_u += -fx * inv_z * dj02 * u_free
        d_v += -fy * inv_z * dj12 * v_free
        d_p0 = _select(ok, d_u * inv_z, 0.0)
        d_p1 = _select(ok, d_v * inv_z, 0.0)
        d_p2 = _select(in_depth, lane[_GZ * _LB + i], 0.0)
        d_p2 = _select(ok, d_p2 + (d_z - (d_u * x + d_v * y) * inv_z * inv_z), d_p2)
        lane[_DM0 * _LB + i] = d_r0 + w[0] * d_p0 + w[3] * d_p1 + w[6] * d_p2
        lane[_DM1 * _LB + i] = d_r1 + w[1] * d_p0 + w[4] * d_p1 + w[7] * d_p2
        lane[_DM2 * _LB + i] = d_r2 + w[2] * d_p0 + w[5] * d_p1 + w[8] * d_p2
