"""Prompt ensembles: each class name embedded under several prompt templates, averaged, re-normalized.

One template ties a class to one phrasing; averaging the L2-normalized embeddings of several phrasings
(CLIP's prompt engineering, Radford et al. 2021) gives a steadier class direction. Each template's
embeddings go through ``text.load_or_encode_texts``, so each is cached in the run folder as the single
template's embeddings are.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Sequence

import torch

from ovgaussian.text.encoders import EMBEDDING_NORM_EPS, load_or_encode_texts
from ovgaussian.run.config import TextConfig

#: Templates of ``--prompt-ensemble`` (indoor-scene phrasings; the training template is the first).
PROMPT_TEMPLATES = (
    "a photo of a {name}.",
    "a {name} in a room.",
    "a photo of the {name} in an indoor scene.",
    "there is a {name} in the scene.",
    "a close-up photo of a {name}.",
    "a 3D model of a {name}.",
)


def ensemble_text_embeddings(names: Sequence[str], config: TextConfig, cache_dir: Path | None,
                             templates: Sequence[str] = PROMPT_TEMPLATES) -> torch.Tensor:
    """``[C, D]``: the mean over ``templates`` of the names' L2-normalized embeddings, L2-normalized again."""
    if not templates:
        raise ValueError("prompt ensemble: no templates")
    stacked = torch.stack([load_or_encode_texts(list(names), replace(config, prompt_template=t), cache_dir).float()
                           for t in templates])  # [T, C, D]
    mean = stacked.mean(dim=0)
    return mean / mean.norm(dim=1, keepdim=True).clamp_min(EMBEDDING_NORM_EPS)
