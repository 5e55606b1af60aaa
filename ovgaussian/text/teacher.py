"""Dense MaskCLIP teacher: per-patch CLIP features of a view, for the visual-semantic loss.

MaskCLIP (Zhou, Loy and Dai, ECCV 2022) reads dense features out of a CLIP ViT by replacing the
query-key attention of the last block with the identity: every patch token keeps its own value.
With transformers' ``CLIPModel`` (or ``CLIPVisionModel`` + a projection) the computation is

    x      = input tokens of the last encoder layer                 [1 + h*w, width]
    v      = out_proj(v_proj(layer_norm1(x)))                          (value path, no q-k attention)
    y      = x + v;  y = y + mlp(layer_norm2(y))                       (residual + MLP, ``residual_mlp``)
    y      = visual_projection(post_layernorm(y))                      [1 + h*w, D]
    patches = y[1:] reshaped to [h, w, D]

With ``residual_mlp=False`` the value path alone goes through post-layernorm and projection.
Images are resized so their short side is ``short_side`` pixels (both sides rounded to whole
patches), normalized with the CLIP mean/std, and run with interpolated position embeddings. The
features stay at patch resolution (small to cache); :func:`sample_patch_features` reads them
bilinearly at pixel centres of the original image (pixel ``(u, v)`` centre at ``u + 0.5, v + 0.5``).
Computed once per view and cached on disk (safetensors) by :meth:`DenseTeacher.cached_patch_features`.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

from ovgaussian.text.encoders import TextEncoderError, check_clip_path
from ovgaussian.run.config import TeacherConfig
from seggaussian.util.atomic import atomic_path

#: OpenAI CLIP image normalization (RGB in [0, 1]).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class TeacherFeatures(NamedTuple):
    """Dense teacher output of one view.

    Fields:
        patch_features: ``[h, w, D]`` float32 MaskCLIP features on the patch grid.
        image_size: ``(height, width)`` of the view the grid covers.
    """

    patch_features: "torch.Tensor"
    image_size: tuple[int, int]


def resized_shape(height: int, width: int, short_side: int, patch_size: int) -> tuple[int, int]:
    """ViT input size: short side ~``short_side``, aspect kept, both sides whole patches (>= 1 patch)."""
    scale = short_side / min(height, width)
    h = max(1, round(height * scale / patch_size)) * patch_size
    w = max(1, round(width * scale / patch_size)) * patch_size
    return h, w


def preprocess_image(rgb: np.ndarray, height: int, width: int) -> "torch.Tensor":
    """uint8 ``[H, W, 3]`` -> normalized ``[1, 3, height, width]`` float32 (bilinear, antialiased)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"teacher: rgb must be [H, W, 3], got shape {rgb.shape}")
    image = torch.from_numpy(np.ascontiguousarray(rgb)).float().div_(255.0).permute(2, 0, 1)[None]
    if image.shape[-2:] != (height, width):
        image = F.interpolate(image, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    mean = torch.tensor(CLIP_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(CLIP_STD).view(1, 3, 1, 1)
    return (image - mean) / std


def encoder_layer_masks(layer) -> dict:
    """No-mask keyword arguments of a transformers ``CLIPEncoderLayer.forward`` (vision: no padding, no
    causal mask). transformers 4.x takes ``(hidden_states, attention_mask, causal_attention_mask,
    output_attentions=False)`` with both masks required; 5.x takes ``(hidden_states, attention_mask,
    **kwargs)``. Both are passed by name, the causal one only where the signature has it."""
    parameters = inspect.signature(layer.forward).parameters
    masks = {"attention_mask": None}
    if "causal_attention_mask" in parameters:
        masks["causal_attention_mask"] = None
    return masks


def maskclip_tokens(vision_model, projection, pixel_values: "torch.Tensor", residual_mlp: bool) -> "torch.Tensor":
    """MaskCLIP tokens ``[B, 1 + h*w, D]`` of a transformers CLIP vision tower (see module doc)."""
    hidden = vision_model.pre_layrnorm(vision_model.embeddings(pixel_values, interpolate_pos_encoding=True))
    layers = vision_model.encoder.layers
    for layer in layers[:-1]:
        hidden = layer(hidden, **encoder_layer_masks(layer))
        hidden = hidden[0] if isinstance(hidden, tuple) else hidden
    last = layers[-1]
    value = last.self_attn.out_proj(last.self_attn.v_proj(last.layer_norm1(hidden)))
    if residual_mlp:
        tokens = hidden + value
        tokens = tokens + last.mlp(last.layer_norm2(tokens))
    else:
        tokens = value
    return projection(vision_model.post_layernorm(tokens))


class DenseTeacher:
    """A frozen CLIP ViT giving MaskCLIP patch features. Build with :meth:`from_config` or from a model."""

    def __init__(self, clip_model, config: TeacherConfig, model_key: str = "in-memory"):
        self.config = config
        self.vision_model = clip_model.vision_model.eval()
        self.projection = clip_model.visual_projection.eval()
        self.patch_size = int(clip_model.config.vision_config.patch_size)
        self.feature_dim = int(self.projection.out_features)
        self.model_key = model_key
        for p in clip_model.parameters():
            p.requires_grad_(False)

    @classmethod
    def from_config(cls, config: TeacherConfig) -> "DenseTeacher":
        """Load the local CLIP named by ``config.clip_model`` (TextEncoderError when missing)."""
        from transformers import CLIPModel  # heavy optional dependency: imported only to load a CLIP

        path = check_clip_path(config.clip_model, "the MaskCLIP teacher (visual-semantic loss)")
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        try:
            model = CLIPModel.from_pretrained(str(path), local_files_only=True)
        except (OSError, ValueError) as error:
            raise TextEncoderError(f"{path}: cannot load a CLIPModel: {error}") from error
        return cls(model, config, model_key=str(path.resolve()))

    @property
    def cache_key(self) -> str:
        """Digest of what determines the features: model, input size rule, residual switch."""
        payload = json.dumps([self.model_key, self.config.short_side, self.config.residual_mlp])
        return hashlib.sha256(payload.encode()).hexdigest()[:16]

    def compute_patch_features(self, rgb: np.ndarray) -> TeacherFeatures:
        """MaskCLIP features ``[h, w, D]`` of one uint8 RGB image ``[H, W, 3]``."""
        height, width = rgb.shape[:2]
        in_h, in_w = resized_shape(height, width, self.config.short_side, self.patch_size)
        pixels = preprocess_image(rgb, in_h, in_w)
        with torch.no_grad():
            tokens = maskclip_tokens(self.vision_model, self.projection, pixels, self.config.residual_mlp)
        grid = tokens[0, 1:].reshape(in_h // self.patch_size, in_w // self.patch_size, -1).float().contiguous()
        return TeacherFeatures(grid, (height, width))

    def cache_path(self, cache_dir: Path, name: str) -> Path:
        """Where :meth:`cached_patch_features` keeps the features of view ``name``."""
        return Path(cache_dir) / f"teacher_{self.cache_key}" / f"{name}.safetensors"

    def cached_patch_features(self, rgb: np.ndarray, cache_dir: Path | None, name: str,
                              may_write: "Callable[[int], bool] | None" = None) -> TeacherFeatures:
        """:meth:`compute_patch_features`, cached as ``cache_dir/teacher_<key>/<name>.safetensors`` (patch
        resolution, float32). ``may_write(nbytes)``: asked before a new file is written (a disk budget);
        when it says no, the features are returned without being cached."""
        if cache_dir is None:
            return self.compute_patch_features(rgb)
        path = self.cache_path(cache_dir, name)
        if path.is_file():
            loaded = load_file(str(path))
            size = tuple(int(x) for x in loaded["image_size"].tolist())
            if size == tuple(rgb.shape[:2]):
                return TeacherFeatures(loaded["patch_features"], size)
        features = self.compute_patch_features(rgb)
        if may_write is not None and not may_write(features.patch_features.numel() * 4):
            return features

        with atomic_path(path) as tmp:
            save_file({"patch_features": features.patch_features,
                       "image_size": torch.tensor(features.image_size, dtype=torch.int64)}, str(tmp))
        return features


def sample_patch_features(
    patch_features: "torch.Tensor",  # [h, w, D]
    pixels: "torch.Tensor",  # [P, 2] int (u = column, v = row) in the original image
    image_size: tuple[int, int],  # (height, width) of the original image
) -> "torch.Tensor":  # [P, D]
    """Bilinear read of the patch grid at pixel centres (grid cells cover the image evenly)."""
    height, width = image_size
    u = (pixels[:, 0].to(patch_features.dtype) + 0.5) / width * 2.0 - 1.0
    v = (pixels[:, 1].to(patch_features.dtype) + 0.5) / height * 2.0 - 1.0
    grid = torch_stack_grid(u, v)
    sampled = F.grid_sample(patch_features.permute(2, 0, 1)[None], grid, mode="bilinear",
                            padding_mode="border", align_corners=False)  # [1, D, 1, P]
    return sampled[0, :, 0].T.contiguous()


def torch_stack_grid(u: "torch.Tensor", v: "torch.Tensor") -> "torch.Tensor":
    """``[1, 1, P, 2]`` grid of normalized (x, y) sampling positions for grid_sample."""
    return torch.stack([u, v], dim=-1)[None, None]


def upsample_patch_features(patch_features: "torch.Tensor", image_size: tuple[int, int]) -> "torch.Tensor":
    """Full-resolution ``[H, W, D]`` teacher features (bilinear, pixel centres); for inspection/small images."""
    out = F.interpolate(patch_features.permute(2, 0, 1)[None], size=image_size, mode="bilinear", align_corners=False)
    return out[0].permute(1, 2, 0).contiguous()
