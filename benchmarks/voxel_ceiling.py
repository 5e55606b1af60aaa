"""How well any model that gives every Gaussian of a voxel one label could score: the voxel-majority ceiling.

    .venv/bin/python benchmarks/voxel_ceiling.py --data out/suite17/dataset --data out/suite17/dataset-oracle

With nearest devoxelization (the profile's default) every Gaussian of a voxel starts from the same backbone
feature, and only the adapter's per-Gaussian attributes can tell them apart. This labels every scored Gaussian with
the most frequent true label of its voxel (ties: the lowest class index), and prints per dataset and voxel edge:
the share of the scored Gaussians whose voxel holds more than one label, and the 3D mIoU of that labelling over
the benchmark vocabulary by the bench's rule (``ovgaussian.metrics``). It reads no model: it bounds what the voxel
grid leaves to the adapter. Issue 27 compares fitted splats with oracle Gaussians of the same rooms; a fit puts
more of its Gaussians where labels meet, so the grid costs it more.

The grid's origin moves with the training's augmentation, so each figure is the mean over ``--origins`` grids
shifted by seeded uniform offsets within one voxel (the first unshifted). Gaussians without a label (beyond the
transfer gate) or of a class outside the vocabulary are not scored and do not vote, as in the bench.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def voxel_majority(means: np.ndarray, labels: np.ndarray, voxel: float, origin: np.ndarray, num_classes: int,
                   ignore: int) -> tuple[np.ndarray, np.ndarray]:
    """(majority label ``[N]``, whether the Gaussian's voxel holds more than one label ``[N]``) of one scene.
    Gaussians labelled ``ignore`` neither vote nor get a label (they keep ``ignore``)."""
    keys = np.floor((means - origin) / voxel).astype(np.int64)
    _, voxel_of = np.unique(keys, axis=0, return_inverse=True)
    voxel_of = voxel_of.reshape(-1)
    scored = labels != ignore
    votes = np.zeros((int(voxel_of.max(initial=-1)) + 1, num_classes), np.int64)
    np.add.at(votes, (voxel_of[scored], labels[scored]), 1)
    majority = np.where(scored, votes.argmax(axis=1)[voxel_of], ignore)
    mixed = (votes > 0).sum(axis=1)[voxel_of] > 1
    return majority, mixed & scored


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, action="append", required=True, help="built dataset (repeatable)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--voxel", type=float, nargs="+", default=[0.1, 0.05, 0.025], help="voxel edges (m)")
    parser.add_argument("--origins", type=int, default=4, help="grid origins averaged (seeded shifts)")
    parser.add_argument("--num-classes", type=int, default=20, help="benchmark vocabulary size K")
    args = parser.parse_args()

    from ovgaussian.metrics import ConfusionMatrix
    from ovgaussian.text.vocabulary import benchmark_vocabulary, to_vocabulary_labels
    from seggaussian import shards
    from seggaussian.core.constants import IGNORE_LABEL

    vocabulary = benchmark_vocabulary(args.num_classes)
    k = len(vocabulary.names)
    print("| dataset | voxel (m) | scored Gaussians | in voxels of more than one label | voxel-majority 3D mIoU |")
    print("|---|---:|---:|---:|---:|")
    for data in args.data:
        scenes = [(np.asarray(s.gaussians.means, np.float64),
                   to_vocabulary_labels(s.gaussians.extras["semantic"], vocabulary))
                  for s in shards.iter_scenes(data, args.split, views=False)]
        scored = sum(int((labels != IGNORE_LABEL).sum()) for _, labels in scenes)
        for voxel in args.voxel:
            rng = np.random.default_rng(0)
            mious, mixed_shares = [], []
            for o in range(args.origins):
                origin = np.zeros(3) if o == 0 else rng.uniform(0.0, voxel, 3)
                matrix, mixed_count = ConfusionMatrix(k), 0
                for means, labels in scenes:
                    majority, mixed = voxel_majority(means, labels, voxel, origin, k, IGNORE_LABEL)
                    matrix.update(majority, labels)
                    mixed_count += int(mixed.sum())
                mious.append(matrix.scores().miou)
                mixed_shares.append(mixed_count / max(scored, 1))
            print(f"| {data} ({args.split}) | {voxel:g} | {scored:,} | {100 * np.mean(mixed_shares):.1f} % | "
                  f"{100 * np.mean(mious):.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
