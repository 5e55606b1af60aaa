"""A view's label map from per-Gaussian vectors: blend weights W, rendered map M = W S, classified per pixel.

Shared by the benchmark's 2D metrics (``bench.py``) and by ``predict.py``'s label maps; streamed in bands
of rows so a view's blend weights and rendered map never exist whole.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import torch

from ovgaussian.predict.config import DEFAULT_BAND_ROWS
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render.pixel_blend import ViewBlender, render_features_no_grad
from seggaussian.render.rasterize import camera_tensors


class BlendFunctions(NamedTuple):
    """How per-Gaussian vectors become a view's rendered map (injectable for tests).

    Fields:
        blend: ``(gaussians, camera, top_k) -> blender`` with ``blender.height`` and
            ``blender.rows(r0, r1) -> BlendWeights`` of the rows ``r0:r1`` (ids ``[R, W, K]``, weights
            ``[R, W, K]``, residual_alpha ``[R, W]``); the view is scored one band of rows at a time.
        render: ``(blend, vectors [N, F]) -> [R, W, F]`` = W S.
    """

    blend: Callable
    render: Callable


def default_blend_functions() -> BlendFunctions:
    """``seggaussian.render``'s blend weights (``ViewBlender``, float64 camera) and M = W S, numpy out."""
    def blend(gaussians, camera, top_k):
        # copies: shard columns are read-only numpy views, which torch.from_numpy warns about
        t = {name: torch.tensor(getattr(gaussians, name)) for name in ("means", "quats", "log_scales", "opacity_logits")}
        viewmat, K = camera_tensors(camera)
        return ViewBlender(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], viewmat, K,
                           camera.width, camera.height, top_k)

    def render_vectors(blend_weights, vectors):  # render.render_features' sum, compiled (no autograd needed)
        return render_features_no_grad(_to_numpy(blend_weights.ids), _to_numpy(blend_weights.weights),
                                       np.asarray(vectors, dtype=np.float32))

    return BlendFunctions(blend, render_vectors)


def accumulated_alpha(blend_weights) -> np.ndarray:
    """``[H, W]`` accumulated alpha of a view: the kept weights plus the residual of the dropped contributors."""
    weights = np.asarray(_to_numpy(blend_weights.weights), dtype=np.float64)
    residual = getattr(blend_weights, "residual_alpha", None)
    alpha = weights.sum(axis=-1)
    if residual is not None:
        alpha = alpha + np.asarray(_to_numpy(residual), dtype=np.float64)
    return alpha


def _to_numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)


def stream_view_labels(classify: Callable[[np.ndarray], np.ndarray], vectors: np.ndarray, blender,
                       functions: BlendFunctions, min_alpha: float, band_rows: int = DEFAULT_BAND_ROWS) -> np.ndarray:
    """``[H, W]`` labels of one view, ``classify(rendered [M, F]) -> [M]`` where the accumulated alpha reaches
    ``min_alpha``, IGNORE_LABEL elsewhere. Rendered ``band_rows`` rows at a time: the view's blend weights and
    rendered map never exist whole (memory ~ band_rows x W x K)."""
    if band_rows < 1:
        raise ValueError(f"band_rows must be >= 1, got {band_rows}")
    height = int(blender.height)
    bands = []
    for r0 in range(0, height, band_rows):
        band = blender.rows(r0, min(height, r0 + band_rows))
        rendered = np.asarray(functions.render(band, vectors))  # [R, W, F]
        h, w = rendered.shape[:2]
        covered = accumulated_alpha(band).reshape(h, w) >= min_alpha
        labels = np.full((h, w), IGNORE_LABEL, dtype=np.int64)
        if covered.any():
            labels[covered] = classify(rendered[covered])
        bands.append(labels)
    return np.concatenate(bands, axis=0)
