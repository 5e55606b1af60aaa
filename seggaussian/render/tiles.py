"""Binning of projected Gaussians into 16x16 pixel tiles, each tile's list in front-to-back order."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.constants import ALPHA_MIN, TILE_SIZE
from seggaussian.render.projection import Projection


class TileBins(NamedTuple):
    """Per-tile Gaussian lists (CSR layout).

    Fields:
        width, height: image size in pixels.
        tiles_x, tiles_y: tile grid size (``ceil(width / TILE_SIZE)``, ...).
        offsets: ``[tiles_x * tiles_y + 1]`` int64: tile t holds ``gaussian_ids[offsets[t]:offsets[t + 1]]``;
            tiles are numbered row-major (``t = ty * tiles_x + tx``).
        gaussian_ids: ``[I]`` int32 Gaussian indices, each tile's run sorted by depth (ties: index order).
    """

    width: int
    height: int
    tiles_x: int
    tiles_y: int
    offsets: np.ndarray
    gaussian_ids: np.ndarray

    @property
    def num_intersections(self) -> int:
        return int(self.gaussian_ids.shape[0])


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
    from seggaussian.render.fast import fill_tile_lists  # numba: imported only when binning

    pixel_box = np.ascontiguousarray(projection.pixel_box.detach().cpu().numpy())
    offsets, ids = fill_tile_lists(order, pixel_box, tiles_x, tiles_y)
    return TileBins(width, height, tiles_x, tiles_y, offsets, ids)
