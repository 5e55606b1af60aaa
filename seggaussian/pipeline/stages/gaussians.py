"""The gaussians stage's output, shared by its three modes: ``gaussians.npz`` (Gaussians + oracle truth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.util.atomic import atomic_path
from seggaussian.core.gaussians import Gaussians

#: Files the stage writes into the scene's cache folder.
OUTPUTS = ("gaussians.npz",)

def save_npz(path: Path, **arrays) -> None:
    """``np.savez`` written atomically (a killed build leaves no partial file)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def save_gaussians(scene_dir: Path, gaussians: Gaussians, truth: np.ndarray | None) -> None:
    """``scene_dir/gaussians.npz``: the geometry and appearance of the Gaussians, plus their true class ``[N]``
    when known (oracle mode)."""
    arrays = dict(means=gaussians.means, quats=gaussians.quats, log_scales=gaussians.log_scales,
                  opacity_logits=gaussians.opacity_logits, sh=gaussians.sh)
    if truth is not None:
        arrays["truth"] = truth
    save_npz(Path(scene_dir) / OUTPUTS[0], **arrays)


def load_gaussians(scene_dir: Path) -> tuple[Gaussians, np.ndarray | None]:
    """What ``save_gaussians`` wrote: (Gaussians, truth ``[N]`` or None)."""
    with np.load(Path(scene_dir) / OUTPUTS[0]) as z:
        g = Gaussians(z["means"], z["quats"], z["log_scales"], z["opacity_logits"], z["sh"])
        truth = z["truth"] if "truth" in z.files and z["truth"].shape == (len(g),) else None
    return g, truth
