"""Per class, where a run's 3D errors are on a split: share of the scored Gaussians, recall, false positives, IoU.

    .venv/bin/python benchmarks/class_precision.py --run out/suite-e30/runs/full --data out/suite-e30/dataset
    .venv/bin/python benchmarks/class_precision.py --run out/suite-e30/runs/full-oracle \\
        --data out/suite-e30/dataset-oracle

Issue 27's 90 % check compares a run trained and scored on fitted splats with one on oracle Gaussians. The 3D IoU
counts Gaussians, and a fit spreads its Gaussians over a room unlike the oracle sampler (first hits of rays through
the views' pixels), so this prints, per benchmark class present in the split: its share of the scored Gaussians,
recall, false positives as a multiple of its own count (and the classes they come from), and IoU, from the bench's
own ``ConfusionMatrix``. Then the mIoU (the bench's 3D CSA on ``val``), and the mIoU with only the Gaussians of
opacity at or above a few thresholds scored. Gaussians without a label (beyond the transfer gate) or of a class
outside the vocabulary are not scored, as in the bench.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="finished run folder")
    parser.add_argument("--data", type=Path, required=True, help="built dataset")
    parser.add_argument("--split", default="val")
    parser.add_argument("--num-classes", type=int, default=20, help="benchmark vocabulary size K")
    args = parser.parse_args()

    from ovgaussian.bench.evaluate import classify_vectors
    from ovgaussian.metrics import ConfusionMatrix
    from ovgaussian.predict.query import load_model_predictor
    from ovgaussian.text.vocabulary import benchmark_vocabulary, to_vocabulary_labels
    from seggaussian import shards
    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.util.threads import cap_threads

    cap_threads(1)
    vocabulary = benchmark_vocabulary(args.num_classes)
    k = len(vocabulary.names)
    predictor = load_model_predictor(args.run)
    thresholds = (0.0, 0.1, 0.3, 0.5)
    matrices = {t: ConfusionMatrix(k) for t in thresholds}  # all scored Gaussians, then opacity >= t only
    total = 0
    for scene in shards.iter_scenes(args.data, args.split, views=False):
        gt = to_vocabulary_labels(scene.gaussians.extras["semantic"], vocabulary)
        pred = classify_vectors(predictor, np.asarray(predictor.encode(scene)), vocabulary)
        opacity = scene.gaussians.opacities()
        total += gt.size
        for t, matrix in matrices.items():
            matrix.update(pred, np.where(opacity >= t, gt, IGNORE_LABEL))
    counts = matrices[0.0].counts  # [K, K+1]: row = truth, column = prediction (K: none)
    scores = matrices[0.0].scores()
    scored = int(counts.sum())
    print(f"{args.run} on {args.data} ({args.split}): {total:,} Gaussians, {scored:,} scored "
          f"({1 - scored / max(total, 1):.1%} not scored: no label, or a class outside the {k}-class vocabulary)")
    print("| class | share | recall | false pos. | from | IoU |\n|---|---:|---:|---:|---|---:|")
    for c in range(k):
        own = int(counts[c].sum())
        if not own:
            continue
        sources = counts[:, c].copy()
        sources[c] = 0  # Gaussians of other classes predicted as c
        top = [f"{vocabulary.names[s]} {sources[s]:,}" for s in np.argsort(-sources)[:3] if sources[s]]
        print(f"| {vocabulary.names[c]} | {own / scored:.1%} | {scores.acc[c]:.0%} | {sources.sum() / own:.2f}x | "
              f"{', '.join(top)} | {100 * scores.iou[c]:.1f} |")
    print(f"mIoU {100 * scores.miou:.1f} (the bench's 3D CSA on val); with only opacity >= 0.1 / 0.3 / 0.5 scored: "
          + " / ".join(f"{100 * matrices[t].scores().miou:.1f}" for t in thresholds[1:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
