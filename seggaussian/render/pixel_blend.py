"""Blend weights W at a set of pixels only: ``M = W S`` for the sampled pixels of a training step.

A training step needs the semantic map at a few thousand sampled pixels of a view, not the whole view.
Storing the whole view's top-k weights (``blend.compute_blend_weights``) costs 16 x (int32 + float32)
per pixel on disk (65 MB per 584x876 view); here they are computed on the fly for the requested pixels:

1. project and bin the Gaussians into 16x16 tiles exactly as ``compute_blend_weights`` does
   (``project_gaussians_fast``, ``bin_gaussians``, float32 2D quantities);
2. group the requested pixels by tile; each tile with requested pixels walks its depth-sorted list
   once, with the requested pixels as the inner, branch-free loop (the layout of ``fast._weights_kernel``,
   with the tile's requested pixels as lanes instead of all 256), and stops once all of them stopped.

Each pixel sees the same Gaussians in the same order with the same float32 arithmetic as in the
full-view kernel, so the result equals the full-view weights gathered at those pixels bit for bit
(``pixel_blend_weights_reference`` is that definition, kept as the reference; the tests compare them).
The cost is proportional to (tiles with requested pixels) x (their list length) x (requested pixels
per tile): for 16,384 of 511,584 pixels about 1/30 of the full view's pixel work.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from seggaussian.core.constants import TILE_SIZE
from seggaussian.render.blend import DEFAULT_TOP_K, compute_blend_weights
from seggaussian.render.inputs import check_inputs
from seggaussian.render.projection_numba import project_gaussians_fast
from seggaussian.render.parallel import run_parallel
from seggaussian.render.rasterize_numba import _DONE_CHECK_EVERY, _HALF, _JIT, _TWO, _ZERO, _blend_step, _f32
from seggaussian.render.results import BlendWeights, TileBins
from seggaussian.render.tiles import bin_gaussians


class PixelBlendWeights(NamedTuple):
    """The top_k front-most contributors of P requested pixels (no gradient).

    Fields:
        ids: ``[P, top_k]`` int64 Gaussian indices in blending order, -1 for unused slots.
        weights: ``[P, top_k]`` float32 blend weights ``alpha_i T_i`` (0 for unused slots).
        residual_alpha: ``[P]`` float32 accumulated alpha of contributors beyond the first top_k.
    """

    ids: Tensor
    weights: Tensor
    residual_alpha: Tensor


def check_pixels(pixels: Tensor, width: int, height: int) -> Tensor:
    """``[P, 2]`` integer (column u, row v) pixels inside the image, as int64 (ValueError otherwise)."""
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixels must be [P, 2] (u, v), got shape {tuple(pixels.shape)}")
    if pixels.dtype.is_floating_point or pixels.dtype == torch.bool:
        raise ValueError(f"pixels must be integers, got {pixels.dtype}")
    pixels = pixels.to(torch.int64)
    if pixels.shape[0]:
        u, v = pixels[:, 0], pixels[:, 1]
        outside = (u < 0) | (u >= width) | (v < 0) | (v >= height)
        if bool(outside.any()):
            first = int(torch.nonzero(outside)[0, 0])
            raise ValueError(f"pixel {tuple(pixels[first].tolist())} lies outside the {width}x{height} image")
    return pixels


def group_pixels_by_tile(
    pixels: np.ndarray,  # [P, 2] int64 (u, v)
    tiles_x: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order [P], tiles [G], starts [G + 1]): pixels ``order[starts[g]:starts[g + 1]]`` lie in tile ``tiles[g]``."""
    tile = (pixels[:, 1] // TILE_SIZE) * tiles_x + pixels[:, 0] // TILE_SIZE
    order = np.argsort(tile, kind="stable")
    tiles, counts = np.unique(tile[order], return_counts=True)
    starts = np.zeros(tiles.shape[0] + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    return order.astype(np.int64), tiles.astype(np.int64), starts


@numba.njit(parallel=True, **_JIT)
def _pixel_weights_kernel(means2d, conics, opacities, offsets, gids, pix_u, pix_v, order, tiles, starts,
                          ids, weights, residual):
    """Per group (a tile and its requested pixels): the walk of ``fast._weights_kernel`` over those pixels."""
    top_k = ids.shape[1]
    for grp in prange(tiles.shape[0]):
        t = tiles[grp]
        p0, p1 = starts[grp], starts[grp + 1]
        lanes = p1 - p0
        px = np.empty(lanes, np.float32)
        py = np.empty(lanes, np.float32)
        for i in range(lanes):
            p = order[p0 + i]
            px[i] = _f32(pix_u[p]) + _HALF
            py[i] = _f32(pix_v[p]) + _HALF
        start, end = offsets[t], offsets[t + 1]
        tr = np.ones(lanes, np.float32)
        active = np.ones(lanes, np.float32)
        weight = np.empty(lanes, np.float32)
        count = np.zeros(lanes, np.int64)
        for k in range(start, end):
            if (k - start) % _DONE_CHECK_EVERY == 0 and k > start:
                if active.sum() == _ZERO:
                    break
            g = gids[k]
            mx, my = means2d[g, 0], means2d[g, 1]
            ca, cb2, cc = conics[g, 0], _TWO * conics[g, 1], conics[g, 2]
            op = opacities[g]
            for i in range(lanes):
                weight[i], tr[i], stop = _blend_step(px[i] - mx, py[i] - my, ca, cb2, cc, op, tr[i], active[i])
                active[i] = active[i] - stop
            for i in range(lanes):
                if weight[i] > _ZERO:
                    p = order[p0 + i]
                    if count[i] < top_k:
                        ids[p, count[i]] = g
                        weights[p, count[i]] = weight[i]
                        count[i] += 1
                    else:
                        residual[p] += weight[i]


def blend_weights_at_pixels_fast(
    means2d: Tensor,  # [N, 2] float32
    conics: Tensor,  # [N, 3] float32
    opacities: Tensor,  # [N] float32
    bins: TileBins,
    pixels: Tensor,  # [P, 2] int64 (u, v), inside the image
    top_k: int,
) -> PixelBlendWeights:
    """The first ``top_k`` blend weights of the requested pixels, from already binned Gaussians."""
    pix = np.ascontiguousarray(pixels.detach().cpu().numpy(), dtype=np.int64)
    num = pix.shape[0]
    ids = np.full((num, top_k), -1, np.int64)
    weights = np.zeros((num, top_k), np.float32)
    residual = np.zeros(num, np.float32)
    if num and bins.num_intersections:
        order, tiles, starts = group_pixels_by_tile(pix, bins.tiles_x)

        def f32(x: Tensor) -> np.ndarray:
            return np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)

        run_parallel(
            _pixel_weights_kernel, f32(means2d), f32(conics), f32(opacities), bins.offsets, bins.gaussian_ids,
            np.ascontiguousarray(pix[:, 0]), np.ascontiguousarray(pix[:, 1]), order, tiles, starts,
            ids, weights, residual,
        )
    return PixelBlendWeights(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(residual))


class ViewBlender:
    """One view's projection and tile bins, computed once; blend weights of any pixels or rows on demand.

    ``at_pixels(pixels)`` serves a training step's sampled pixels; ``rows(r0, r1)`` serves a band of whole
    rows (the 2D benchmark streams a view band by band, so memory is bounded by the band, not the view).
    Both equal ``compute_blend_weights`` of the whole view at those pixels, bit for bit. Inputs may live
    on any device; the work and the results are on the CPU.
    """

    def __init__(
        self,
        means: Tensor,  # [N, 3]
        quats: Tensor,  # [N, 4]
        log_scales: Tensor,  # [N, 3]
        opacity_logits: Tensor,  # [N]
        viewmat: Tensor,  # [4, 4] (float64, as the build renders its label maps)
        K: Tensor,  # [3, 3]
        width: int,
        height: int,
        top_k: int = DEFAULT_TOP_K,
    ) -> None:
        if int(top_k) < 1:
            raise ValueError(f"blend weights: top_k must be >= 1, got {top_k}")
        self.width, self.height, self.top_k = int(width), int(height), int(top_k)
        with torch.no_grad():
            means, quats, log_scales, opacity_logits, viewmat, K = (
                t.detach().cpu() for t in (means, quats, log_scales, opacity_logits, viewmat, K))
            check_inputs(means, quats, log_scales, opacity_logits, viewmat, K, self.width, self.height)
            self.opacities = torch.sigmoid(opacity_logits.to(torch.float32))
            projection = project_gaussians_fast(means, quats, log_scales, viewmat, K, self.width, self.height)
            self.means2d, self.conics = projection.means2d.float(), projection.conics.float()
            self.bins = bin_gaussians(projection, self.width, self.height, self.opacities)

    def at_pixels(self, pixels: Tensor) -> PixelBlendWeights:  # pixels: [P, 2] int (u, v)
        """Blend weights of the requested pixels (``[P, top_k]``)."""
        pixels = check_pixels(pixels.detach().cpu(), self.width, self.height)
        return blend_weights_at_pixels_fast(self.means2d, self.conics, self.opacities, self.bins, pixels, self.top_k)

    def rows(self, row_start: int, row_stop: int) -> BlendWeights:
        """Blend weights of the rows ``row_start:row_stop`` as an image ``[rows, W, top_k]``."""
        if not 0 <= row_start < row_stop <= self.height:
            raise ValueError(f"rows {row_start}:{row_stop} are not a non-empty band of the {self.height} rows")
        v, u = torch.meshgrid(torch.arange(row_start, row_stop), torch.arange(self.width), indexing="ij")
        found = self.at_pixels(torch.stack([u.reshape(-1), v.reshape(-1)], dim=1))
        shape = (row_stop - row_start, self.width)
        return BlendWeights(found.ids.reshape(*shape, self.top_k), found.weights.reshape(*shape, self.top_k),
                            found.residual_alpha.reshape(shape))


def compute_pixel_blend_weights(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] (float64, as the build renders its label maps)
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    pixels: Tensor,  # [P, 2] int (u, v)
    top_k: int = DEFAULT_TOP_K,
) -> PixelBlendWeights:
    """``compute_blend_weights(...)`` at ``pixels`` only (bit-identical to gathering the full view's weights)."""
    return ViewBlender(means, quats, log_scales, opacity_logits, viewmat, K, width, height, top_k).at_pixels(pixels)


def pixel_blend_weights_reference(
    means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, viewmat: Tensor, K: Tensor,
    width: int, height: int, pixels: Tensor, top_k: int = DEFAULT_TOP_K, *, backend: str = "fast",
) -> PixelBlendWeights:
    """The definition: the whole view's ``compute_blend_weights`` (what used to be cached on disk), gathered."""
    pixels = check_pixels(pixels.detach().cpu(), int(width), int(height))
    full = compute_blend_weights(means, quats, log_scales, opacity_logits, viewmat, K, width, height, top_k,
                                 backend=backend)
    u, v = pixels[:, 0], pixels[:, 1]
    return PixelBlendWeights(full.ids[v, u].clone(), full.weights[v, u].clone(), full.residual_alpha[v, u].clone())



@numba.njit(parallel=True, cache=True, nogil=True)
def _render_kernel(ids, weights, features, out):
    """out[p] = sum_k weights[p, k] * features[ids[p, k]] over used slots, slot by slot (render_features' order)."""
    dim = features.shape[1]
    for p in prange(ids.shape[0]):
        for k in range(ids.shape[1]):
            g = ids[p, k]
            if g >= 0:
                w = weights[p, k]
                for d in range(dim):
                    out[p, d] = out[p, d] + w * features[g, d]


def render_features_no_grad(
    ids: np.ndarray,  # [..., top_k] int Gaussian ids (-1 unused)
    weights: np.ndarray,  # [..., top_k] float32 blend weights
    features: np.ndarray,  # [N, D] float32
) -> np.ndarray:  # [..., D] float32
    """``M = W S`` without autograd (evaluation): ``blend.render_features``' sum, compiled and parallel."""
    ids = np.asarray(ids)
    shape = ids.shape[:-1]
    flat_ids = np.ascontiguousarray(ids.reshape(-1, ids.shape[-1]), dtype=np.int64)
    flat_w = np.ascontiguousarray(np.asarray(weights).reshape(flat_ids.shape), dtype=np.float32)
    features = np.ascontiguousarray(features, dtype=np.float32)
    if flat_ids.size and int(flat_ids.max()) >= features.shape[0]:
        raise ValueError(f"render_features_no_grad: weights refer to Gaussian {int(flat_ids.max())} "
                         f"but features has {features.shape[0]} rows")
    out = np.zeros((flat_ids.shape[0], features.shape[1]), np.float32)
    if out.size:
        run_parallel(_render_kernel, flat_ids, flat_w, features, out, chunk=1024)
    return out.reshape(*shape, features.shape[1])
