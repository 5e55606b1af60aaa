"""Per class, where a run's 3D errors are on a split: share of the scored Gaussians, recall, false positives, IoU.

    .venv/bin/python benchmarks/class_precision.py --run out/suite-e30/runs/full --data out/suite-e30/dataset
    .venv/bin/python benchmarks/class_precision.py --run out/suite-e30/runs/full-oracle --data out/suite-e30/dataset-oracle

Issue 27's 90 % check compares a run trained and scored on fitted splats with one on oracle Gaussians. The 3D IoU
counts Gaussians, and a fit spreads its Gaussians over a room unlike the oracle sampler (first hits of rays through the views' pixels), so this prints,
per benchmark class present in the split: its share of the scored Gaussians, recall, false positives as a multiple of
its own count (and the classes they come from), and IoU. Then the pooled mIoU (equal to the bench's 3D CSA on
``val``), and the pooled mIoU with only the Gaussians of opacity at or above a few thresholds scored. Gaussians without
a label (beyond the transfer gate) or of a class outside the vocabulary are not scored, as in the bench.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def pooled_miou(pred: np.ndarray, gt: np.ndarray, classes: np.ndarray) -> float:
    """Mean over ``classes`` present in ``gt`` of the pooled IoU, in percent."""
    ious = [np.sum((pred == c) & (gt == c)) / np.sum((pred == c) | (gt == c)) for c in classes if np.any(gt == c)]
    return 100.0 * float(np.mean(ious)) if ious else float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="finished run folder")
    parser.add_argument("--data", type=Path, required=True, help="built dataset")
    parser.add_argument("--split", default="val")
    parser.add_argument("--num-classes", type=int, default=20, help="benchmark vocabulary size K")
    args = parser.parse_args()

    from ovgaussian.bench.evaluate import classify_vectors
    from ovgaussian.predict.query import load_model_predictor
    from ovgaussian.text.vocabulary import benchmark_vocabulary, to_vocabulary_labels
    from seggaussian import shards
    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.util.threads import cap_threads

    cap_threads(1)
    vocabulary = benchmark_vocabulary(args.num_classes)
    predictor = load_model_predictor(args.run)
    preds, gts, opacities, total = [], [], [], 0
    for scene in shards.iter_scenes(args.data, args.split, views=False):
        gt = to_vocabulary_labels(scene.gaussians.extras["semantic"], vocabulary)
        pred = classify_vectors(predictor, np.asarray(predictor.encode(scene)), vocabulary)
        scored = gt != IGNORE_LABEL
        total += gt.size
        preds.append(pred[scored])
        gts.append(gt[scored])
        opacities.append(scene.gaussians.opacities()[scored])
    pred, gt, opacity = np.concatenate(preds), np.concatenate(gts), np.concatenate(opacities)
    classes = np.arange(len(vocabulary.names))
    print(f"{args.run} on {args.data} ({args.split}): {total:,} Gaussians, {gt.size:,} scored "
          f"({1 - gt.size / max(total, 1):.1%} not scored: no label, or a class outside the {len(vocabulary.names)}-class "
          "vocabulary)")
    print("| class | share | recall | false pos. | from | IoU |\n|---|---:|---:|---:|---|---:|")
    for c in classes:
        own = gt == c
        if not own.any():
            continue
        false = (pred == c) & ~own
        sources = np.bincount(gt[false], minlength=classes.size)
        top = [f"{vocabulary.names[s]} {sources[s]:,}" for s in np.argsort(-sources)[:3] if sources[s]]
        iou = np.sum((pred == c) & own) / np.sum((pred == c) | own)
        print(f"| {vocabulary.names[c]} | {own.mean():.1%} | {np.mean(pred[own] == c):.0%} | "
              f"{false.sum() / own.sum():.2f}x | {', '.join(top)} | {100 * iou:.1f} |")
    print(f"pooled mIoU {pooled_miou(pred, gt, classes):.1f}; with only opacity >= 0.1 / 0.3 / 0.5 scored: "
          + " / ".join(f"{pooled_miou(pred[opacity >= t], gt[opacity >= t], classes):.1f}" for t in (0.1, 0.3, 0.5)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
