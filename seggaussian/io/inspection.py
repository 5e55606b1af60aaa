"""``seggaussian inspect`` for one splat file: format, layout, statistics and the validation report (nothing changed)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import detect_format, read_gaussians_raw
from seggaussian.io.ply.header import read_ply_header
from seggaussian.io.ply.reader import read_vertex_table, vertex_table_to_gaussians
from seggaussian.io.splat_common import FORMAT_TITLES
from seggaussian.io.validate import validate_gaussians

#: Quantiles reported for scales and opacities.
QUANTILES = (0.0, 0.05, 0.5, 0.95, 1.0)


def _stats(values: np.ndarray) -> dict:
    """min / quantiles / max / mean over the finite values of ``values`` (all None when there are none)."""
    finite = values[np.isfinite(values)].astype(np.float64)
    if finite.size == 0:
        return {"count": 0, "mean": None, "quantiles": {str(q): None for q in QUANTILES}}
    return {
        "count": int(finite.size),
        "mean": float(finite.mean()),
        "quantiles": {str(q): float(v) for q, v in zip(QUANTILES, np.quantile(finite, QUANTILES))},
    }


def summarize_gaussians(gaussians: Gaussians) -> dict:
    """Count, SH degree, bounds, scale / opacity / colour / quaternion-norm statistics (finite values only)."""
    g = gaussians
    finite_means = g.means[np.isfinite(g.means).all(axis=1)]
    with np.errstate(over="ignore", invalid="ignore"):
        scales = np.exp(g.log_scales.astype(np.float64))
    colors = g.dc_colors()
    finite_colors = colors[np.isfinite(colors).all(axis=1)]
    return {
        "num_gaussians": len(g),
        "sh_degree": g.sh_degree,
        "extras": {name: str(column.dtype) + (f"x{column.shape[1]}" if column.ndim == 2 else "")
                   for name, column in g.extras.items()},
        "bounds": {
            "min": finite_means.min(axis=0).tolist() if len(finite_means) else None,
            "max": finite_means.max(axis=0).tolist() if len(finite_means) else None,
        },
        "scale": _stats(scales),
        "opacity": _stats(g.opacities()),
        "dc_color": {
            "mean": finite_colors.mean(axis=0).tolist() if len(finite_colors) else None,
            "share_outside_0_1": float(((finite_colors < 0) | (finite_colors > 1)).any(axis=1).mean())
            if len(finite_colors) else None,
        },
        "quat_norm": _stats(np.linalg.norm(g.quats.astype(np.float64), axis=1)),
    }


def inspect_ply(path: str | os.PathLike) -> dict:
    """Header layout, ``summarize_gaussians`` and the validation report (policy ``report``) of a PLY."""
    header = read_ply_header(path)
    table = read_vertex_table(path, header)
    gaussians = vertex_table_to_gaussians(table, source=header.path)
    _, report = validate_gaussians(gaussians, on_invalid="report", source=str(header.path))
    vertex = header.element("vertex")
    return {
        "path": str(Path(path)),
        "format": header.format,
        "file_bytes": header.file_size,
        "num_properties": len(vertex.properties),
        "has_normals": all(n in {p.name for p in vertex.properties} for n in ("nx", "ny", "nz")),
        **summarize_gaussians(gaussians),
        "validation": report.to_dict(),
    }


def inspect_scene(path: str | os.PathLike) -> dict:
    """``inspect_ply`` for any splat file: ``file_format`` names the detected format (``ply``,
    ``compressed_ply``, ``splat``, ``spz``) and ``format_title`` says it in words."""
    fmt = detect_format(path)
    if fmt == "ply":
        info = inspect_ply(path)
    else:
        gaussians, _ = read_gaussians_raw(path, fmt)
        _, report = validate_gaussians(gaussians, on_invalid="report", source=f"{path} ({FORMAT_TITLES[fmt]})")
        info = {"path": str(Path(path)), "format": fmt, "file_bytes": Path(path).stat().st_size,
                "num_properties": None, "has_normals": False, **summarize_gaussians(gaussians),
                "validation": report.to_dict()}
    return {**info, "file_format": fmt, "format_title": FORMAT_TITLES[fmt]}
