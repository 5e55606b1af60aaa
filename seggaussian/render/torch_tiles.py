"""Pure-torch blending vectorized over tiles (autograd), the baseline the fast kernels are measured against.

Same rule as ``reference.py``; the per-pixel stop is expressed with cumulative products: a pixel's
transmittance after Gaussian k (counting every Gaussian with alpha >= ALPHA_MIN) falls monotonically,
so "stop at the first Gaussian that would take it below TRANSMITTANCE_MIN" keeps exactly the Gaussians
whose inclusive product is still >= TRANSMITTANCE_MIN.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from seggaussian.core.constants import ALPHA_MAX, ALPHA_MIN, RADIUS_SIGMAS, TILE_SIZE, TRANSMITTANCE_MIN
from seggaussian.render.results import TileBins

#: Upper bound on (tiles x 256 pixels x padded list length) evaluated at once, to bound memory.
CHUNK_PAIRS = 4_000_000


def blend_torch_tiles(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D]
    bins: TileBins,
) -> tuple[Tensor, Tensor]:  # accumulated colours [H, W, D], accumulated alpha [H, W]
    dtype, dim = colors.dtype, colors.shape[1]
    tile_px = TILE_SIZE * TILE_SIZE
    num_tiles = bins.tiles_x * bins.tiles_y
    lengths = np.diff(bins.offsets)
    accum_tiles = torch.zeros(num_tiles, tile_px, dim, dtype=dtype)
    alpha_tiles = torch.zeros(num_tiles, tile_px, dtype=dtype)
    local = torch.arange(tile_px)
    ids_np = bins.gaussian_ids.astype(np.int64)
    order = np.argsort(lengths, kind="stable")  # similar lengths share a chunk: little padding
    order = order[lengths[order] > 0]
    accum_parts, alpha_parts, tile_parts = [], [], []
    pos = 0
    while pos < len(order):
        end = pos + 1
        while end < len(order) and (end - pos + 1) * tile_px * int(lengths[order[end]]) <= CHUNK_PAIRS:
            end += 1
        tiles = order[pos:end]
        longest = int(lengths[tiles].max())
        pad = np.full((len(tiles), longest), -1, np.int64)
        for row, t in enumerate(tiles):
            pad[row, : lengths[t]] = ids_np[bins.offsets[t] : bins.offsets[t + 1]]
        idx = torch.from_numpy(pad)
        present = idx >= 0  # [C, L]
        safe = idx.clamp_min(0)
        tt = torch.from_numpy(tiles)
        px = ((tt % bins.tiles_x)[:, None] * TILE_SIZE + local % TILE_SIZE).to(dtype) + 0.5  # [C, 256]
        py = ((tt // bins.tiles_x)[:, None] * TILE_SIZE + local // TILE_SIZE).to(dtype) + 0.5
        dx = px[:, :, None] - means2d[safe][:, None, :, 0]  # [C, 256, L]
        dy = py[:, :, None] - means2d[safe][:, None, :, 1]
        con = conics[safe][:, None]  # [C, 1, L, 3]
        s = con[..., 0] * dx * dx + 2.0 * con[..., 1] * dx * dy + con[..., 2] * dy * dy
        alpha = torch.clamp(opacities[safe][:, None, :] * torch.exp(-0.5 * s.clamp_min(0.0)), max=ALPHA_MAX)
        use = (s <= RADIUS_SIGMAS**2) & (alpha >= ALPHA_MIN) & present[:, None, :]
        a = torch.where(use, alpha, torch.zeros_like(alpha))
        keep = torch.cumprod(1.0 - a.detach(), -1) >= TRANSMITTANCE_MIN
        a = torch.where(keep, a, torch.zeros_like(a))
        trans_incl = torch.cumprod(1.0 - a, -1)
        trans_before = torch.cat([torch.ones_like(trans_incl[..., :1]), trans_incl[..., :-1]], -1)
        weights = a * trans_before  # [C, 256, L]
        accum_parts.append(torch.einsum("cpl,cld->cpd", weights, colors[safe]))
        alpha_parts.append(1.0 - trans_incl[..., -1])
        tile_parts.append(tt)
        pos = end
    if tile_parts:
        tt = torch.cat(tile_parts)
        accum_tiles = accum_tiles.index_put((tt,), torch.cat(accum_parts))
        alpha_tiles = alpha_tiles.index_put((tt,), torch.cat(alpha_parts))
    anchor = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + colors.sum())  # stay in the graph
    accum_tiles, alpha_tiles = accum_tiles + anchor, alpha_tiles + anchor
    th, tw = bins.tiles_y * TILE_SIZE, bins.tiles_x * TILE_SIZE
    accum = accum_tiles.reshape(bins.tiles_y, bins.tiles_x, TILE_SIZE, TILE_SIZE, dim).permute(0, 2, 1, 3, 4)
    alpha = alpha_tiles.reshape(bins.tiles_y, bins.tiles_x, TILE_SIZE, TILE_SIZE).permute(0, 2, 1, 3)
    accum = accum.reshape(th, tw, dim)[: bins.height, : bins.width]
    alpha = alpha.reshape(th, tw)[: bins.height, : bins.width]
    return accum, alpha
