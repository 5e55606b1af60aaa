"""Binning of projected Gaussians into 16x16 pixel tiles, each tile's list in front-to-back order."""

from __future__ import annotations

import numpy as np

from seggaussian.constants import ALPHA_MIN, TILE_SIZE
from seggaussian.render.projection import Projection
from seggaussian.render.rasterize_numba import fill_tile_lists
from seggaussian.render.results import TileBins


def bin_gaussians(
    projection: Projection,
    width: int,
    height: int,
    opacities=None,  # [N] optional: Gaussians with opacity < ALPHA_MIN can never blend and are skipped
) -> TileBins:
    """Sort the valid Gaussians by depth (stable) and append each to every tile its pixel box touches."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    valid = projection.valid.detach().cpu().numpy()
    if opacities is not None:
        valid = valid & (opacities.detach().cpu().numpy() >= ALPHA_MIN)
    idx = np.flatnonzero(valid)
    depths = projection.depths.detach().cpu().numpy().astype(np.float64)[idx]
    order = idx[np.argsort(depths, kind="stable")].astype(np.int64)

    pixel_box = np.ascontiguousarray(projection.pixel_box.detach().cpu().numpy())
    offsets, ids = fill_tile_lists(order, pixel_box, tiles_x, tiles_y)
    return TileBins(width, height, tiles_x, tiles_y, offsets, ids)
