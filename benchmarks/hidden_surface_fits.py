"""Benchmark: which label the transfer gives a fitted Gaussian near a surface no view sees, against what the Gaussian
is seen as in the images.

For every room asked for, the stored (fitted) Gaussians of a built dataset are labelled again by the transfer stage
(``seggaussian.pipeline.stages.transfer.run_transfer``) at several ``on_surface_tolerance`` values (0 turns the
hidden-surface rule off: no Gaussian keeps an unseen surface's label). Each labelling is compared with the label each
Gaussian is *seen as*: over every view of the room, each pixel's ray hits the mesh (open3d), the hit face's label is
that of its corner of largest barycentric weight (the rule of the transfer's mesh samples), and the pixel's blend
weights (our rasterizer's top-K contributors) vote that label for its Gaussians; a Gaussian is seen as the label of
most weight, when its votes sum to at least ``--min-weight``. Gaussians no view shows enough are left out.

Prints, per room and tolerance, how many Gaussians the rule moved to another label than the rule-off labelling and how
many of those agree with what they are seen as, before and after the move; then the totals.

    .venv/bin/python benchmarks/hidden_surface_fits.py --raw RAW --data DATASET [--split val] [--rooms 4]
        [--tolerances 0,0.0005,0.001,0.003]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def seen_labels(scene, gaussians, min_weight: float) -> np.ndarray:
    """``[N]`` the label each Gaussian is seen as in the scene's views (IGNORE_LABEL: too little weight or none)."""
    import torch

    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.render.pixel_blend import ViewBlender
    from seggaussian.sources.raycast import MeshRaycaster

    caster = MeshRaycaster(scene.points, scene.faces)
    faces = np.asarray(scene.faces)
    classes = int(scene.semantic[scene.semantic != IGNORE_LABEL].max(initial=0)) + 1
    votes = np.zeros((len(gaussians.means), classes))
    g = gaussians
    for view in scene.views:
        camera = view.camera
        hits = caster.cast(camera)
        hit = hits.face_ids >= 0
        u, v = hits.barycentric[..., 0], hits.barycentric[..., 1]
        corner = np.argmax(np.stack([1.0 - u - v, u, v], axis=-1), axis=-1)
        vertex = faces[np.where(hit, hits.face_ids, 0), corner]
        label = np.where(hit, scene.semantic[vertex], IGNORE_LABEL).reshape(-1)
        blender = ViewBlender(*(torch.from_numpy(np.ascontiguousarray(a)) for a in (
            g.means, g.quats, g.log_scales, g.opacity_logits)), torch.from_numpy(camera.viewmat),
            torch.from_numpy(camera.K), camera.width, camera.height)
        rows = blender.rows(0, camera.height)
        ids = rows.ids.reshape(-1, rows.ids.shape[-1]).numpy()
        weights = rows.weights.reshape(-1, rows.weights.shape[-1]).numpy()
        keep = (ids >= 0) & (label[:, None] != IGNORE_LABEL) & (weights > 0)
        np.add.at(votes, (ids[keep], np.broadcast_to(label[:, None], ids.shape)[keep]), weights[keep])
    seen = np.argmax(votes, axis=1)
    return np.where(votes.sum(axis=1) >= min_weight, seen, IGNORE_LABEL)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--raw", type=Path, required=True, help="raw tree the dataset was built from")
    parser.add_argument("--data", type=Path, required=True, help="built dataset of fitted splats")
    parser.add_argument("--split", default="val")
    parser.add_argument("--rooms", type=int, default=4)
    parser.add_argument("--tolerances", default="0,0.0005,0.001,0.003")
    parser.add_argument("--min-weight", type=float, default=0.5)
    args = parser.parse_args()

    from seggaussian import shards
    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.fit.optimize import read_source_scene
    from seggaussian.labels.config import TransferConfig
    from seggaussian.pipeline.config import BuildConfig
    from seggaussian.pipeline.stages.transfer import run_transfer

    tolerances = sorted({0.0, *(float(t) for t in args.tolerances.split(","))})  # 0: the rule off, the baseline
    totals = {t: np.zeros(4, np.int64) for t in tolerances}
    print("| room | tolerance | Gaussians seen | moved by the rule | of those, seen as the rule's label | seen as the "
          "label without the rule |\n|---|---:|---:|---:|---:|---:|")
    for scene_id in shards.list_scenes(args.data, args.split)[: args.rooms]:
        record = shards.read_scene(args.data, args.split, scene_id, views=False)
        scene = read_source_scene("synthetic", args.raw, scene_id)
        gaussians = record.gaussians
        seen = seen_labels(scene, gaussians, args.min_weight)
        shown = seen != IGNORE_LABEL
        labels = {}
        for tolerance in tolerances:
            config = BuildConfig(source="synthetic", root=args.raw, out=args.data,
                                 transfer=replace(TransferConfig(), on_surface_tolerance=tolerance))
            labelled, _ = run_transfer(scene, gaussians, None, config)
            labels[tolerance] = labelled.extras["semantic"]
        off = labels[0.0]
        for tolerance in tolerances:
            if tolerance == 0.0:
                continue
            moved = shown & (labels[tolerance] != off)
            row = np.array([shown.sum(), moved.sum(), (moved & (seen == labels[tolerance])).sum(),
                            (moved & (seen == off)).sum()])
            totals[tolerance] += row
            print(f"| {scene_id} | {tolerance:g} | {row[0]:,} | {row[1]:,} | {row[2]:,} | {row[3]:,} |", flush=True)
    for tolerance, row in totals.items():
        if tolerance == 0.0:
            continue
        print(f"| all | {tolerance:g} | {row[0]:,} | {row[1]:,} ({100 * row[1] / max(row[0], 1):.2f} %) | {row[2]:,} "
              f"| {row[3]:,} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
