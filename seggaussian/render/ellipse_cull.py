"""Ellipse culling of tile boxes: which tiles of a Gaussian's pixel box its blending ellipse reaches.

A Gaussian blends at a pixel centre only where its Mahalanobis^2 ``m`` is at most ``RADIUS_SIGMAS^2`` and its alpha
``opacity exp(-m / 2)`` at least ``ALPHA_MIN``: inside the ellipse ``m <= r2`` with ``r2 = min(RADIUS_SIGMAS^2,
2 ln(opacity / ALPHA_MIN))`` (the opacity-aware radius). The projection's pixel box holds the 3-sigma ellipse's
axis-aligned extent, so a rotated, elongated or faint Gaussian leaves tiles of its box that it blends in nowhere.

``cull_lanes`` (numba, float64, branch-free over a block of ``LANE_BLOCK`` Gaussians staged as columns, as in
``projection_lanes``) shrinks each box to the ellipse's extent and, for each of its first ``TRIM_ROWS`` tile rows,
trims the tiles left and right of the ellipse's span over that row's pixel centres. The span over a band of rows
follows from the extreme points: the ellipse's left edge x(dy) is convex with its minimum at the leftmost point, the
right edge concave with its maximum at the rightmost, so each is evaluated at that point clamped to the band.

The test is conservative: ``r2`` is widened by ``CULL_REL_MARGIN`` and ``CULL_ABS_MARGIN`` and every span by
``CULL_PIXEL_MARGIN`` pixels against the float32 arithmetic of the blending kernels, and trims are capped at
``MAX_TRIM`` tiles per side. A dropped (Gaussian, tile) pair therefore blends at no pixel of the tile, and images,
blend weights and gradients equal those of the whole boxes. ``tiles_reached_reference`` is the brute-force check:
the tiles where some pixel centre passes the kernels' rule, evaluated pixel by pixel.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from seggaussian.core.constants import ALPHA_MIN, RADIUS_SIGMAS, TILE_SIZE
from seggaussian.render.projection_lanes import _LB, _select

_JIT = dict(cache=True, nogil=True, error_model="numpy")

#: Tile rows per box whose tiles outside the ellipse are trimmed (the packed box keeps 4 bits per row).
TRIM_ROWS = 4
#: Largest trim on either side of a row (2 bits); a wider gap keeps the excess tiles (conservative).
MAX_TRIM = 3
#: Margins against float32 rounding in the kernels (whose Mahalanobis^2 and alpha are float32): the cut-off is
#: widened to ``r2 (1 + CULL_REL_MARGIN) + CULL_ABS_MARGIN`` and every span by ``CULL_PIXEL_MARGIN`` pixels on each
#: side (the projection's box has the same pixel margin, ``TILE_MARGIN_PX``).
CULL_REL_MARGIN = 1e-3
CULL_ABS_MARGIN = 1e-3
CULL_PIXEL_MARGIN = 1.0
_CUTOFF2 = RADIUS_SIGMAS * RADIUS_SIGMAS
_INV_TILE = 1.0 / TILE_SIZE
assert TILE_SIZE & (TILE_SIZE - 1) == 0, "tile indices are exact products by 1 / TILE_SIZE"

# Blocks of LANE_BLOCK Gaussians as in the projection (15 float64 columns: 7.5 KB of scratch, within L1).
# scratch columns: inputs (pixel box, centre, conic, cut-off), then outputs (tile box, trims)
_U0, _V0, _U1, _V1, _MX, _MY, _CA, _CB, _CC, _R2 = (np.uint64(k) for k in range(10))
TX0, TY0, TX1, TY1, TRIMS = (np.uint64(k) for k in range(10, 15))
LANE_FIELDS = 15


#: Opacities at or above this blend out to the full RADIUS_SIGMAS (2 ln(o / ALPHA_MIN) >= RADIUS_SIGMAS^2).
OPACITY_FULL_RADIUS = ALPHA_MIN * math.exp(_CUTOFF2 / 2.0)


@numba.njit(inline="always", **_JIT)
def cull_radius2(opacity):
    """A Gaussian's widened cut-off: ``min(RADIUS_SIGMAS^2, 2 ln(opacity / ALPHA_MIN))`` (alpha falls below ALPHA_MIN
    past it) ``(1 + CULL_REL_MARGIN) + CULL_ABS_MARGIN``; a negative opacity means none given (RADIUS_SIGMAS^2).
    Opacities below ALPHA_MIN (never binned) count as ALPHA_MIN. The log only where it binds."""
    r2 = _CUTOFF2
    if 0.0 <= opacity < OPACITY_FULL_RADIUS:
        r2 = 2.0 * math.log(max(opacity, ALPHA_MIN) * (1.0 / ALPHA_MIN))
    return r2 * (1.0 + CULL_REL_MARGIN) + CULL_ABS_MARGIN


@numba.njit(inline="always", **_JIT)
def stage(lane, i, u0, v0, u1, v1, mx, my, ca, cb, cc, r2):
    """Write Gaussian ``i`` of a block into its scratch columns (all as float64)."""
    lane[_U0 * _LB + i] = np.float64(u0)
    lane[_V0 * _LB + i] = np.float64(v0)
    lane[_U1 * _LB + i] = np.float64(u1)
    lane[_V1 * _LB + i] = np.float64(v1)
    lane[_MX * _LB + i] = mx
    lane[_MY * _LB + i] = my
    lane[_CA * _LB + i] = ca
    lane[_CB * _LB + i] = cb
    lane[_CC * _LB + i] = cc
    lane[_R2 * _LB + i] = r2


@numba.njit(**_JIT)
def cull_lanes(lane):
    """One block: from the input columns (pixel box ``u0 v0 u1 v1``, inclusive and >= 0; centre; conic ``ca cb cc``,
    Mahalanobis^2 = ca dx^2 + 2 cb dx dy + cc dy^2; cut-off ``r2``) the output columns: the tile box ``TX0 TY0 TX1
    TY1`` and ``TRIMS`` (row k's left trim times 16^k plus its right trim times 4 x 16^k), all exact integers.

    A conic that is not positive definite and finite keeps its whole box. An ellipse over no pixel centre gives an
    empty box (first tile row one after the last). A row the ellipse misses is trimmed as far as MAX_TRIM allows.
    """
    for i in range(_LB):
        u0, v0, u1, v1 = lane[_U0 * _LB + i], lane[_V0 * _LB + i], lane[_U1 * _LB + i], lane[_V1 * _LB + i]
        mx, my, r2 = lane[_MX * _LB + i], lane[_MY * _LB + i], lane[_R2 * _LB + i]
        ca, cb, cc = lane[_CA * _LB + i], lane[_CB * _LB + i], lane[_CC * _LB + i]
        det = ca * cc - cb * cb
        ok = ((det > 0.0) & (ca > 0.0) & (cc > 0.0) & math.isfinite(det) & math.isfinite(mx) & math.isfinite(my)
              & math.isfinite(r2) & (r2 > 0.0))
        det = _select(ok, det, 1.0)
        ca = _select(ok, ca, 1.0)
        cc = _select(ok, cc, 1.0)
        cb = _select(ok, cb, 0.0)
        mx = _select(ok, mx, 0.0)
        my = _select(ok, my, 0.0)
        r2 = _select(ok, r2, 1.0)
        inv_det = 1.0 / det
        inv_ca = 1.0 / ca
        ext_x = math.sqrt(r2 * cc * inv_det)  # sqrt(r2 cov_xx)
        ext_y = math.sqrt(r2 * ca * inv_det)
        # pixel p's centre is p + 0.5: the centres in [m - ext - margin, m + ext + margin]
        pu0 = max(u0, np.ceil(mx - ext_x - (CULL_PIXEL_MARGIN + 0.5)))
        pu1 = min(u1, np.floor(mx + ext_x + (CULL_PIXEL_MARGIN - 0.5)))
        pv0 = max(v0, np.ceil(my - ext_y - (CULL_PIXEL_MARGIN + 0.5)))
        pv1 = min(v1, np.floor(my + ext_y + (CULL_PIXEL_MARGIN - 0.5)))
        empty = ok & ((pu0 > pu1) | (pv0 > pv1))
        reached = ok & (pu0 <= pu1) & (pv0 <= pv1)
        pu0 = _select(ok, pu0, u0)
        pu1 = _select(ok, pu1, u1)
        pv0 = _select(ok, pv0, v0)
        pv1 = _select(ok, pv1, v1)
        tx0 = np.floor(pu0 * _INV_TILE)
        tx1 = np.floor(pu1 * _INV_TILE)
        ty0 = np.floor(pv0 * _INV_TILE)
        ty1 = np.floor(pv1 * _INV_TILE)
        trim = reached & (tx1 > tx0) & (ty1 > ty0)
        width = tx1 - tx0 + 1.0
        empty_left = min(float(MAX_TRIM), width)
        empty_right = min(float(MAX_TRIM), width - empty_left)
        dy_left = cb * inv_det * r2 / ext_x  # the leftmost point's dy (-r cov_xy / sqrt(cov_xx)); rightmost: -dy_left
        trims = 0.0
        weight = 1.0
        for k in range(TRIM_ROWS):
            band0 = (ty0 + k) * TILE_SIZE
            lo = max(max(pv0, band0) + (0.5 - CULL_PIXEL_MARGIN) - my, -ext_y)
            hi = min(min(pv1, band0 + (TILE_SIZE - 1)) + (0.5 + CULL_PIXEL_MARGIN) - my, ext_y)
            dl = min(max(dy_left, lo), hi)
            dr = min(max(-dy_left, lo), hi)
            x_left = mx - (cb * dl + math.sqrt(max(0.0, ca * r2 - det * dl * dl))) * inv_ca
            x_right = mx + (math.sqrt(max(0.0, ca * r2 - det * dr * dr)) - cb * dr) * inv_ca
            c0 = max(pu0, np.ceil(x_left - (CULL_PIXEL_MARGIN + 0.5)))
            c1 = min(pu1, np.floor(x_right + (CULL_PIXEL_MARGIN - 0.5)))
            hit = (lo <= hi) & (c0 <= c1)
            left = _select(hit, min(float(MAX_TRIM), np.floor(c0 * _INV_TILE) - tx0), empty_left)
            right = _select(hit, min(float(MAX_TRIM), tx1 - np.floor(c1 * _INV_TILE)), empty_right)
            code = _select(trim & (ty0 + k <= ty1), left + 4.0 * right, 0.0)
            trims += code * weight
            weight *= 16.0
        lane[TX0 * _LB + i] = _select(empty, np.floor(u0 * _INV_TILE), tx0)
        lane[TX1 * _LB + i] = _select(empty, np.floor(u0 * _INV_TILE), tx1)
        lane[TY0 * _LB + i] = _select(empty, np.floor(v0 * _INV_TILE) + 1.0, ty0)
        lane[TY1 * _LB + i] = _select(empty, np.floor(v0 * _INV_TILE), ty1)
        lane[TRIMS * _LB + i] = _select(empty, 0.0, trims)


def tiles_reached_reference(
    means2d: np.ndarray,  # [N, 2]
    conics: np.ndarray,  # [N, 3]
    opacities: np.ndarray | None,  # [N]
    pixel_box: np.ndarray,  # [N, 4] inclusive (u0, v0, u1, v1)
    tiles_x: int,
) -> list[set[int]]:
    """For each Gaussian, the tiles of its pixel box holding a pixel centre where the blending kernels' rule passes,
    evaluated pixel by pixel in float32 as they do: ``s = ca dx^2 + 2 cb dx dy + cc dy^2 <= RADIUS_SIGMAS^2`` and
    ``opacity exp(-s / 2) >= ALPHA_MIN`` (the alpha clamp only lowers alpha above ALPHA_MAX). Slow: tests only."""
    f32 = np.float32
    out = []
    for g in range(len(means2d)):
        u0, v0, u1, v1 = (int(v) for v in pixel_box[g])
        reached: set[int] = set()
        if u0 <= u1 and v0 <= v1:
            px, py = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
            dx = (px.astype(f32) + f32(0.5)) - f32(means2d[g, 0])
            dy = (py.astype(f32) + f32(0.5)) - f32(means2d[g, 1])
            ca, cb2, cc = f32(conics[g, 0]), f32(2.0) * f32(conics[g, 1]), f32(conics[g, 2])
            s = ca * dx * dx + cb2 * dx * dy + cc * dy * dy
            op = f32(1.0 if opacities is None else opacities[g])
            alpha = op * np.exp(f32(-0.5) * np.maximum(s, f32(0.0)))
            hit = (s <= f32(_CUTOFF2)) & (alpha >= f32(ALPHA_MIN))
            tiles = (py[hit] // TILE_SIZE) * tiles_x + px[hit] // TILE_SIZE
            reached = set(int(t) for t in np.unique(tiles))
        out.append(reached)
    return out
