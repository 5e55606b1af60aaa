"""Diagnostic (issue 16): can the text embeddings name the unseen classes on a trained model's vectors?

For the Gaussians of the first ``--scenes`` scenes of a split whose truth is an unseen class, the model's scores
against the K-class benchmark vocabulary are restricted to the unseen columns and arg-maxed (``restricted``), and
again after standardizing each unseen column over those Gaussians (``standardized``). Prints, per true unseen
class, the share of its Gaussians given each unseen name. A diagnostic: it reads the unseen labels, which no
method may do.

    .venv/bin/python benchmarks/unseen_name_probe.py out/suite-trans/runs/full out/suite-trans/dataset --scenes 12
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ovgaussian.predict.query import load_model_predictor  # noqa: E402
from ovgaussian.data.scene_source import ShardSource  # noqa: E402
from ovgaussian.text.vocabulary import benchmark_vocabulary, to_vocabulary_labels  # noqa: E402


def shares(chosen: np.ndarray, truth: np.ndarray, names: list[str]) -> dict:
    """``{true name: {given name: share}}`` over the unseen classes (indices into ``names``)."""
    out = {}
    for t in np.unique(truth):
        given = chosen[truth == t]
        out[names[t]] = {names[g]: round(float(np.mean(given == g)), 3) for g in np.unique(chosen)}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="run folder of ovgaussian train")
    parser.add_argument("dataset", type=Path, help="dataset folder")
    parser.add_argument("--split", default="train")
    parser.add_argument("--scenes", type=int, default=12, help="first N scenes of the split")
    parser.add_argument("--classes", type=int, default=20, help="vocabulary size K")
    args = parser.parse_args(argv)
    vocabulary = benchmark_vocabulary(args.classes)
    predictor = load_model_predictor(args.run)
    source = ShardSource(args.dataset, args.split)
    scores, truth = [], []
    for scene_id in source.list_scenes()[:args.scenes]:
        record = source.read_scene(scene_id)
        labels = to_vocabulary_labels(record.gaussians.extras["semantic"], vocabulary, scene_id)
        keep = np.isin(labels, vocabulary.unseen)
        if keep.any():
            vectors = predictor.encode(record)[keep]
            scores.append(np.asarray(predictor.classify(vectors, vocabulary.class_ids))[:, vocabulary.unseen])
            truth.append(labels[keep])
    if not scores:
        raise SystemExit(f"{args.dataset}: no Gaussian of an unseen class in the first {args.scenes} scenes")
    unseen_scores, truth = np.concatenate(scores), np.concatenate(truth)
    standardized = (unseen_scores - unseen_scores.mean(0)) / np.maximum(unseen_scores.std(0), 1e-12)
    names = list(vocabulary.names)
    print(json.dumps({
        "gaussians": int(truth.size),
        "restricted": shares(vocabulary.unseen[np.argmax(unseen_scores, 1)], truth, names),
        "standardized": shares(vocabulary.unseen[np.argmax(standardized, 1)], truth, names),
    }, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
