"""``seggaussian export-ply``: one scene of a built dataset as a 3DGS PLY with its label vertex properties."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.labels.palette import build_legend, colour_by_labels, write_legend
from seggaussian.shards.read import find_split, read_scene


def export_scene_ply(dataset: Path, scene_id: str, out: Path, color_by: str | None = None) -> dict:
    """``seggaussian export-ply``: one scene's Gaussians with semantic and instance vertex properties.

    ``color_by`` (``semantic`` or ``instance``): the DC colour becomes the label's palette colour (higher SH
    zeroed, ``seggaussian.labels.palette``) and a legend JSON + PNG is written beside ``out``.
    """
    if color_by not in (None, "semantic", "instance"):
        raise ValueError(f"color_by must be semantic or instance, got {color_by!r}")
    split = find_split(dataset, scene_id)
    record = read_scene(dataset, split, scene_id, views=False)
    g = record.gaussians
    keep = {k: g.extras[k].astype(np.int32) for k in ("semantic", "instance")}
    keep["transfer_distance"] = g.extras["transfer_distance"].astype(np.float32)
    plain = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, keep)
    if color_by is not None:
        plain = colour_by_labels(plain, keep[color_by])
    write_gaussians_ply(out, plain)
    legend = []
    if color_by is not None:
        names = read_class_names() if color_by == "semantic" else None
        legend = [str(p) for p in write_legend(out, build_legend(keep[color_by], color_by, names))]
    sem = keep["semantic"]
    return {"scene": scene_id, "split": split, "gaussians": len(g), "labelled": int((sem != IGNORE_LABEL).sum()),
            "out": str(out), "color_by": color_by, "legend": legend}
