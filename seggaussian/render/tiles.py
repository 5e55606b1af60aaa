"""Binning of projected Gaussians into 16x16 pixel tiles, each tile's list in front-to-back order.

``bin_gaussians`` sorts by depth with a parallel radix sort and fills the tiles with a parallel counting sort
(``binning_numba``); ``bin_gaussians_argsort`` is the former path (a stable ``argsort`` and a fill by bands of
tile rows), kept as the reference the tests compare against and as the benchmark's "before". Both give the
same lists when ``bin_gaussians`` fills whole boxes (``ellipse_cull=False``): valid Gaussians by increasing depth,
equal depths in index order. By default ``bin_gaussians`` leaves out the tiles of a box that the Gaussian's blending
ellipse misses (``binning_numba``, "Ellipse culling"): each tile's list is then that list less Gaussians that blend
at none of its pixels, which changes no image, weight or gradient; ``ellipse_cull.tiles_reached_reference`` is the
brute-force check of which tiles a Gaussian can blend in.
"""

from __future__ import annotations

import numpy as np

from seggaussian.core.constants import ALPHA_MIN, TILE_SIZE
from seggaussian.render.binning_fill import fill_tile_lists
from seggaussian.render.binning_numba import bin_sorted
from seggaussian.render.projection import Projection
from seggaussian.render.results import TileBins


def _selected(projection: Projection, opacities) -> np.ndarray:  # ascending int64 indices
    valid = projection.valid.detach().cpu().numpy()
    if opacities is not None:
        valid = valid & (opacities.detach().cpu().numpy() >= ALPHA_MIN)
    return np.flatnonzero(valid)


def _box_rows(projection: Projection) -> np.ndarray:  # [N, 2] int32 (v_min, v_max)
    return np.ascontiguousarray(projection.pixel_box.detach().cpu().numpy()[:, 1::2], dtype=np.int32)


def _tile_grid(width: int, height: int) -> tuple[int, int]:
    return (width + TILE_SIZE - 1) // TILE_SIZE, (height + TILE_SIZE - 1) // TILE_SIZE


def bin_gaussians(
    projection: Projection,
    width: int,
    height: int,
    opacities=None,  # [N] optional: Gaussians with opacity < ALPHA_MIN can never blend and are skipped
    ellipse_cull: bool = True,
) -> TileBins:
    """Sort the valid Gaussians by depth (stable) and append each to the tiles of its pixel box: those its blending
    ellipse reaches (opacity-aware when ``opacities`` are given), or every one with ``ellipse_cull=False``."""
    tiles_x, tiles_y = _tile_grid(width, height)
    idx = _selected(projection, opacities)
    means2d = conics = opac = None
    if ellipse_cull:
        means2d, conics = projection.means2d.detach().cpu().numpy(), projection.conics.detach().cpu().numpy()
        opac = None if opacities is None else opacities.detach().cpu().numpy()
    offsets, ids, _ = bin_sorted(
        idx, projection.depths.detach().cpu().numpy(), projection.pixel_box.detach().cpu().numpy(), TILE_SIZE,
        tiles_x, tiles_y, means2d, conics, opac)
    return TileBins(width, height, tiles_x, tiles_y, offsets, ids, _box_rows(projection))


def bin_gaussians_argsort(projection: Projection, width: int, height: int, opacities=None) -> TileBins:
    """The former binning (stable argsort by depth, fill by bands of tile rows): reference and benchmark only."""
    tiles_x, tiles_y = _tile_grid(width, height)
    idx = _selected(projection, opacities)
    depths = projection.depths.detach().cpu().numpy().astype(np.float64)[idx]
    order = idx[np.argsort(depths, kind="stable")].astype(np.int64)
    pixel_box = np.ascontiguousarray(projection.pixel_box.detach().cpu().numpy())
    offsets, ids = fill_tile_lists(order, pixel_box, tiles_x, tiles_y)
    return TileBins(width, height, tiles_x, tiles_y, offsets, ids, _box_rows(projection))
