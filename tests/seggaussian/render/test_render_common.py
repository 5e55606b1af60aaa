"""Shared small synthetic scenes for the seggaussian.render tests (helpers only, no tests here)."""

from __future__ import annotations

import numpy as np
import torch

from seggaussian.core.cameras import intrinsics, look_at

WIDTH, HEIGHT = 32, 24


def camera(width: int = WIDTH, height: int = HEIGHT, eye=(0.3, -3.0, 0.6)):
    """(viewmat [4, 4] float64, K [3, 3] float64) looking at the origin."""
    viewmat = torch.from_numpy(look_at(np.asarray(eye, float), [0.0, 0.0, 0.0]))
    K = torch.from_numpy(intrinsics(0.9 * width, 0.9 * width, width / 2 + 0.3, height / 2 - 0.2))
    return viewmat, K


def random_scene(num: int, seed: int, dtype=torch.float32, sh_degree: int = 1, spread: float = 0.6):
    """dict of means, quats, log_scales, opacity_logits, sh [N, (d+1)^2, 3], features [N, 5]."""
    g = torch.Generator().manual_seed(seed)
    return {
        "means": (torch.randn(num, 3, generator=g) * spread).to(dtype),
        "quats": torch.randn(num, 4, generator=g).to(dtype),
        "log_scales": (torch.randn(num, 3, generator=g) * 0.4 - 2.0).to(dtype),
        "opacity_logits": (torch.randn(num, generator=g) * 1.5 + 0.5).to(dtype),
        "sh": (torch.randn(num, (sh_degree + 1) ** 2, 3, generator=g) * 0.4).to(dtype),
        "features": torch.rand(num, 5, generator=g).to(dtype),
    }


GEOMETRY = ("means", "quats", "log_scales", "opacity_logits")
