"""Validation of the renderer's inputs (shapes, finiteness), shared by every entry point."""

from __future__ import annotations

import numpy as np
from torch import Tensor


def check_finite(name: str, x: Tensor | None, allow_inf: bool = False) -> None:
    """ValueError naming ``name`` when ``x`` holds NaN (or Inf unless ``allow_inf``).

    Checked with numpy on a zero-copy view: single-threaded, so it costs no torch thread synchronization.
    """
    if x is None or x.numel() == 0:
        return
    values = x.detach().cpu().numpy()
    bad = np.isnan(values) if allow_inf else ~np.isfinite(values)
    if bad.any():
        kind = "NaN" if allow_inf else "NaN/Inf"
        raise ValueError(f"rasterize: {name} holds {kind} ({int(bad.sum())} values)")


def check_inputs(means, quats, log_scales, opacity_logits, viewmat, K, width, height) -> int:
    """Validate shapes and values; returns N. ``log_scales`` and ``opacity_logits`` may be +-inf."""
    n = check_gaussians(means, quats, log_scales, opacity_logits)
    check_camera(viewmat, K, width, height)
    return n


def check_gaussians(means, quats, log_scales, opacity_logits) -> int:
    """The Gaussians' part of :func:`check_inputs`: shapes, finite means and quaternions; returns N."""
    n = means.shape[0] if means.ndim == 2 else -1
    for name, x, shape in (
        ("means", means, (n, 3)), ("quats", quats, (n, 4)), ("log_scales", log_scales, (n, 3)),
        ("opacity_logits", opacity_logits, (n,)),
    ):
        if tuple(x.shape) != shape or n < 0:
            raise ValueError(f"rasterize: {name} has shape {tuple(x.shape)}, expected {shape}")
    for name, x in (("means", means), ("quats", quats)):
        check_finite(name, x)
    check_finite("log_scales", log_scales, allow_inf=True)
    check_finite("opacity_logits", opacity_logits, allow_inf=True)
    return n


def check_camera(viewmat, K, width, height) -> None:
    """The camera's part of :func:`check_inputs`: a finite ``[4, 4]`` viewmat and ``[3, 3]`` K, a positive size."""
    for name, x, shape in (("viewmat", viewmat, (4, 4)), ("K", K, (3, 3))):
        if tuple(x.shape) != shape:
            raise ValueError(f"rasterize: {name} has shape {tuple(x.shape)}, expected {shape}")
        check_finite(name, x)
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"rasterize: image size must be positive, got {width}x{height}")
