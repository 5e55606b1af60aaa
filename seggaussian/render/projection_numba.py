"""EWA projection as fused numba kernels (float64 arithmetic, parallel over blocks of Gaussians), forward and backward.

Same mathematics, culling and outputs as ``projection.project_gaussians`` (the torch version, which is
the reference the tests compare against). Each block of ``LANE_BLOCK`` Gaussians is staged as float64 columns and
projected on SIMD lanes by the kernels of ``projection_lanes``; the outputs are copied back row-wise.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from seggaussian.render.projection import Projection, camera_centre
from seggaussian.render.projection_lanes import (
    _BOK, _CA, _CB, _CC, _DEPTH, _DL0, _DL1, _DL2, _DM0, _DM1, _DM2, _DQ0, _DQ1, _DQ2, _DQ3, _GC0, _GC1, _GC2,
    _GD0, _GD1, _GD2, _GM0, _GM1, _GZ, _LB, _MX, _MY, _OK, _U0, _U1, _V0, _V1, _VD0, _VD1, _VD2, BACKWARD_FIELDS,
    LANE_BLOCK, LANE_FIELDS, _f64, forward_params, open_block, project_backward_lanes, project_lanes,
)
from seggaussian.render.parallel import GAUSSIANS_PER_CHUNK, run_parallel

_JIT = dict(cache=True, nogil=True, error_model="numpy")

# The copies between rows and columns below are written out field by field. A generic helper looping over an array's
# columns (``rows.shape[1]``, a run-time width) was measured slower at 1M: kernel forward 22-27 against 20-22 ms,
# backward 33-39 against 29-37 ms (alternated, scratch timing).


@numba.njit(parallel=True, **_JIT)
def _project_forward(means, quats, log_scales, centre, params,
                     means2d, conics, depths, valid, pixel_box, view_dirs):
    """Parallel over blocks of ``LANE_BLOCK`` Gaussians: each block's inputs are copied into float64 columns, projected
    by :func:`project_lanes` on SIMD lanes, and its outputs copied back row-wise. No temporary array but the block's
    scratch columns."""
    for blk in prange((means.shape[0] + LANE_BLOCK - 1) // LANE_BLOCK):
        lane, lo, count = open_block(blk, LANE_FIELDS, means, quats, log_scales, centre)
        project_lanes(lane, params)
        for i in range(count):
            n = lo + i
            view_dirs[n, 0] = lane[_VD0 * _LB + i]
            view_dirs[n, 1] = lane[_VD1 * _LB + i]
            view_dirs[n, 2] = lane[_VD2 * _LB + i]
            depths[n] = lane[_DEPTH * _LB + i]
            means2d[n, 0] = lane[_MX * _LB + i]
            means2d[n, 1] = lane[_MY * _LB + i]
            conics[n, 0] = lane[_CA * _LB + i]
            conics[n, 1] = lane[_CB * _LB + i]
            conics[n, 2] = lane[_CC * _LB + i]
            valid[n] = lane[_OK * _LB + i] != 0.0
            pixel_box[n, 0] = np.int64(lane[_U0 * _LB + i])
            pixel_box[n, 1] = np.int64(lane[_V0 * _LB + i])
            pixel_box[n, 2] = np.int64(lane[_U1 * _LB + i])
            pixel_box[n, 3] = np.int64(lane[_V1 * _LB + i])


@numba.njit(parallel=True, **_JIT)
def _project_backward(means, quats, log_scales, centre, params, valid, g_means2d, g_conics, g_depths, g_dirs,
                      d_means, d_quats, d_log_scales):
    """Chain rule of ``_project_forward``, in the forward's blocks: inputs and output gradients staged as columns,
    :func:`project_backward_lanes` on SIMD lanes, the input gradients copied back row-wise."""
    for blk in prange((means.shape[0] + LANE_BLOCK - 1) // LANE_BLOCK):
        lane, lo, count = open_block(blk, BACKWARD_FIELDS, means, quats, log_scales, centre)
        for i in range(count):
            n = lo + i
            lane[_BOK * _LB + i] = 1.0 if valid[n] else 0.0
            lane[_GM0 * _LB + i] = _f64(g_means2d[n, 0])
            lane[_GM1 * _LB + i] = _f64(g_means2d[n, 1])
            lane[_GC0 * _LB + i] = _f64(g_conics[n, 0])
            lane[_GC1 * _LB + i] = _f64(g_conics[n, 1])
            lane[_GC2 * _LB + i] = _f64(g_conics[n, 2])
            lane[_GZ * _LB + i] = _f64(g_depths[n])
            lane[_GD0 * _LB + i] = _f64(g_dirs[n, 0])
            lane[_GD1 * _LB + i] = _f64(g_dirs[n, 1])
            lane[_GD2 * _LB + i] = _f64(g_dirs[n, 2])
        project_backward_lanes(lane, params)
        for i in range(count):
            n = lo + i
            d_means[n, 0] = lane[_DM0 * _LB + i]
            d_means[n, 1] = lane[_DM1 * _LB + i]
            d_means[n, 2] = lane[_DM2 * _LB + i]
            d_quats[n, 0] = lane[_DQ0 * _LB + i]
            d_quats[n, 1] = lane[_DQ1 * _LB + i]
            d_quats[n, 2] = lane[_DQ2 * _LB + i]
            d_quats[n, 3] = lane[_DQ3 * _LB + i]
            d_log_scales[n, 0] = lane[_DL0 * _LB + i]
            d_log_scales[n, 1] = lane[_DL1 * _LB + i]
            d_log_scales[n, 2] = lane[_DL2 * _LB + i]


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
            run_parallel(_project_forward, *arrays, centre, forward_params(w2c, cam, width, height), means2d, conics,
                         depths, valid, pixel_box, view_dirs, chunk=max(1, GAUSSIANS_PER_CHUNK // LANE_BLOCK))
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
            run_parallel(_project_backward, *arrays, centre, forward_params(w2c, cam, width, height), valid,
                         grad(g_means2d, (n, 2)), grad(g_conics, (n, 3)), grad(g_depths, (n,)),
                         grad(g_dirs, (n, 3)), d_means, d_quats, d_log_scales,
                         chunk=max(1, GAUSSIANS_PER_CHUNK // LANE_BLOCK))
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
