"""The render result types, shared by every backend and by the callers of the renderer.

Kept apart from the modules that compute them so that the numba kernels, the torch backends and the
dispatch in ``rasterize.py`` can all import them without importing each other.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from torch import Tensor


class RenderOutput(NamedTuple):
    """A rendered view.

    Fields:
        image: ``[H, W, D]`` blended colours/features plus ``(1 - alpha) * background``.
        alpha: ``[H, W]`` accumulated opacity ``1 - T``.
        depth: ``[H, W]`` expected camera depth of the blended Gaussians, ``sum w z / alpha`` (0 where
            nothing was blended).
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor


class TileBins(NamedTuple):
    """Per-tile Gaussian lists (CSR layout).

    Fields:
        width, height: image size in pixels.
        tiles_x, tiles_y: tile grid size (``ceil(width / TILE_SIZE)``, ...).
        offsets: ``[tiles_x * tiles_y + 1]`` int64: tile t holds ``gaussian_ids[offsets[t]:offsets[t + 1]]``;
            tiles are numbered row-major (``t = ty * tiles_x + tx``).
        gaussian_ids: ``[I]`` int32 Gaussian indices, each tile's run sorted by depth (ties: index order).
        rows: ``[N, 2]`` int32 ``(v_min, v_max)``: the pixel rows of each Gaussian's box (the projection's
            ``pixel_box``); the kernels skip a tile's rows outside it, where the 3-sigma cut-off fails anyway.
    """

    width: int
    height: int
    tiles_x: int
    tiles_y: int
    offsets: np.ndarray
    gaussian_ids: np.ndarray
    rows: np.ndarray

    @property
    def num_intersections(self) -> int:
        return int(self.gaussian_ids.shape[0])


class BlendWeights(NamedTuple):
    """The top_k front-most contributors of every pixel of one view (no gradient).

    Fields:
        ids: ``[H, W, top_k]`` int64 Gaussian indices in blending order, -1 for unused slots.
        weights: ``[H, W, top_k]`` float32 blend weights ``alpha_i T_i`` (0 for unused slots).
        residual_alpha: ``[H, W]`` float32 accumulated alpha of contributors beyond the first top_k
            (total accumulated alpha = weights.sum(-1) + residual_alpha).
    """

    ids: Tensor
    weights: Tensor
    residual_alpha: Tensor
