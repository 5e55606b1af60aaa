"""What every splat-format reader and writer shares: the error type, file reading, quantisation helpers.

A malformed file raises :class:`SplatFormatError`, whose message names the file, the format and what is
wrong. It subclasses :class:`~seggaussian.io.ply.header.PlyFormatError`, so every entry point that already turns
a bad PLY into a one-line message does the same for every other format.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from seggaussian.core.constants import SH_C0
from seggaussian.io.ply.header import PlyFormatError

__all__ = [
    "SplatFormatError",
    "FORMAT_TITLES",
    "UNIT_OPACITY_EPS",
    "read_file_bytes",
    "logit_from_unit",
    "unit_from_logit",
    "dc_from_rgb",
    "rgb_from_dc",
    "unorm_to_byte",
    "require_finite",
]

#: Human names of the formats, used in every error message.
FORMAT_TITLES = {
    "ply": "3DGS PLY",
    "compressed_ply": "compressed PLY (SuperSplat / PlayCanvas)",
    "splat": "antimatter15 .splat",
    "spz": "Niantic SPZ",
    "ksplat": "mkkellogg .ksplat",
    "gltf": "glTF (KHR_gaussian_splatting)",
}

#: An 8-bit opacity a/255 is clamped to [eps, 1 - eps] before the logit, so a stored 0 or 255 becomes a
#: finite logit (+-13.8) instead of +-inf; the same clamp as @playcanvas/splat-transform's .splat/.spz readers.
UNIT_OPACITY_EPS = 1e-6


class SplatFormatError(PlyFormatError):
    """A splat file that cannot be read; the message names the file, the format and the problem."""


def read_file_bytes(path: str | os.PathLike, title: str) -> bytes:
    """The whole file; ``SplatFormatError`` for OS errors and empty files."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SplatFormatError(f"{path}: cannot read the {title} file ({exc.strerror or exc})") from None
    if not data:
        raise SplatFormatError(f"{path}: empty file (0 bytes), not a {title} file")
    return data


def logit_from_unit(values: np.ndarray) -> np.ndarray:
    """``[...]`` opacities in [0, 1] -> float32 logits, clamped by ``UNIT_OPACITY_EPS``."""
    a = np.clip(values.astype(np.float32), np.float32(UNIT_OPACITY_EPS), np.float32(1.0 - UNIT_OPACITY_EPS))
    return np.log(a / (np.float32(1.0) - a)).astype(np.float32)


def unit_from_logit(logits: np.ndarray) -> np.ndarray:
    """``[...]`` logits -> opacities in [0, 1] (float64 tanh form: no overflow warnings)."""
    return 0.5 * (1.0 + np.tanh(0.5 * logits.astype(np.float64)))


def dc_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """``[..., 3]`` colours in [0, 1] -> float32 ``f_dc`` (colour = 0.5 + SH_C0 * f_dc)."""
    return ((rgb.astype(np.float32) - np.float32(0.5)) / np.float32(SH_C0)).astype(np.float32)


def rgb_from_dc(dc: np.ndarray) -> np.ndarray:
    """``[..., 3]`` ``f_dc`` -> colours (not clamped), float64."""
    return 0.5 + SH_C0 * dc.astype(np.float64)


def unorm_to_byte(values: np.ndarray) -> np.ndarray:
    """``[...]`` values in [0, 1] -> uint8 ``round(v * 255)``, clamped; NaN -> 0."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0)
    return np.clip(np.round(v * 255.0), 0, 255).astype(np.uint8)


def require_finite(gaussians, title: str) -> None:
    """``ValueError`` (one line, naming the format and the field) when a splat attribute of ``gaussians`` holds
    NaN/Inf: every writer refuses them rather than storing them."""
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        if not np.isfinite(getattr(gaussians, name)).all():
            raise ValueError(f"{title}: Gaussians.{name} holds NaN/Inf; validate (or repair) before writing")
