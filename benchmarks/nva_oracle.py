"""What caps NVA (issue 16): the ground-truth Gaussian labels scored through the bench's 2D pipeline, and the
unseen classes' share of a trained model's NVA.

The oracle predictor encodes each Gaussian as the one-hot vector of its stored top-100 label, so its 2D
scores say how much the rendering path (blend weights, alpha threshold, argmax of blended vectors) loses
against the stored label maps. With a bench report (``ovgaussian bench --out REPORT``), it also prints
``ovgaussian.metrics.unseen_share`` of the report's NVA confusion matrix.

    .venv/bin/python benchmarks/nva_oracle.py out/bench-suite/dataset
    .venv/bin/python benchmarks/nva_oracle.py out/bench-suite/dataset --report out/bench-suite/reports/table1-02.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ovgaussian.bench import run_bench  # noqa: E402
from ovgaussian.bench_config import BenchConfig  # noqa: E402
from ovgaussian.metrics import unseen_share  # noqa: E402
from seggaussian.constants import IGNORE_LABEL  # noqa: E402

#: Width of the one-hot vectors: top-100 ids 0..99 and one column for every other label (ignore included).
WIDTH = 101


class OraclePredictor:
    """``encode``: one-hot of each Gaussian's stored label; ``classify``: the columns of the asked classes."""

    name = "ground-truth oracle"

    def encode(self, scene) -> np.ndarray:
        semantic = np.asarray(scene.gaussians.extras["semantic"], dtype=np.int64)  # [N]
        vectors = np.zeros((semantic.size, WIDTH), np.float32)  # [N, 101]
        known = (semantic >= 0) & (semantic < WIDTH - 1) & (semantic != IGNORE_LABEL)
        vectors[np.nonzero(known)[0], semantic[known]] = 1.0
        vectors[~known, WIDTH - 1] = 1.0
        return vectors

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        return vectors[:, class_ids].astype(np.float64)  # [M, K]


def _pct(value: float | None) -> float | None:
    return None if value is None else round(100 * value, 2)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="dataset folder (splits train/val)")
    parser.add_argument("--max-views", type=int, default=4, help="views per scene, as the profile (4)")
    parser.add_argument("--report", type=Path, help="a bench report whose NVA is split into the unseen share")
    args = parser.parse_args(argv)
    config = BenchConfig(dataset=args.dataset, predictor="majority", metrics=("CSA", "NVA"), dims=("2d",),
                         max_views_per_scene=args.max_views)
    result = run_bench(config, OraclePredictor()).result
    out = {f"oracle 2D {metric}": _pct(result.results[("2d", metric)].scores.miou) for metric in ("CSA", "NVA")}
    if args.report is not None:
        payload = json.loads(args.report.read_text())
        names = payload["vocabulary"]["names"]
        share = unseen_share(np.asarray(payload["confusion"]["train_2d"]),
                             [names.index(n) for n in payload["vocabulary"]["unseen"]])
        out.update({f"report NVA {field}": _pct(value) for field, value in share._asdict().items()})
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
