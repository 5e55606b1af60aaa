"""One differentiable 3D Gaussian rasterizer for everything (RGB, features, depth, blend weights, labels).

Public API (torch tensors in and out; see docs/INTERFACES.md):

- ``rasterize(...) -> RenderOutput(image, alpha, depth)``: differentiable in every Gaussian input.
- ``compute_blend_weights(...) -> BlendWeights(ids, weights, residual_alpha)``: top_k front-most contributors.
- ``render_features(blend, features) -> [H, W, D]``: M = W S, differentiable in features.
- ``render_label_maps(blend, semantic, instance, num_classes) -> LabelMaps(semantic, instance, soft)``.
- ``render_gaussians(gaussians, camera, ...)``: the numpy ``Gaussians`` / ``Camera`` convenience.
"""

from seggaussian.render.blend import DEFAULT_TOP_K, compute_blend_weights, render_features
from seggaussian.render.labelmaps import LABEL_MIN_ALPHA, LabelMaps, render_label_maps
from seggaussian.render.projection import Projection, project_gaussians
from seggaussian.render.rasterize import rasterize, render_gaussians
from seggaussian.render.results import BlendWeights, RenderOutput

__all__ = [
    "BlendWeights",
    "DEFAULT_TOP_K",
    "LABEL_MIN_ALPHA",
    "LabelMaps",
    "Projection",
    "RenderOutput",
    "compute_blend_weights",
    "project_gaussians",
    "rasterize",
    "render_features",
    "render_gaussians",
    "render_label_maps",
]
