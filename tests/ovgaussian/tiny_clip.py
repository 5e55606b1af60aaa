"""A randomly initialised, tiny transformers CLIP for the tests that need a teacher (no weights on disk)."""

from __future__ import annotations

import torch
from transformers import CLIPConfig, CLIPModel


def random_clip(vision_width: int = 16, vision_layers: int = 1, image_size: int = 16, patch_size: int = 8,
                projection_dim: int = 20) -> CLIPModel:
    """A CLIP with a one-layer 16-wide text tower and the given vision tower, seeded with ``torch.manual_seed(0)``."""
    torch.manual_seed(0)
    return CLIPModel(CLIPConfig(
        text_config=dict(hidden_size=16, intermediate_size=16, num_hidden_layers=1, num_attention_heads=2,
                         vocab_size=40, max_position_embeddings=8, bos_token_id=0, eos_token_id=1, pad_token_id=1),
        vision_config=dict(hidden_size=vision_width, intermediate_size=vision_width, num_hidden_layers=vision_layers,
                           num_attention_heads=2, image_size=image_size, patch_size=patch_size),
        projection_dim=projection_dim)).eval()
