"""What caps NVA (issue 16): the ground-truth Gaussian labels scored through the bench's 2D pipeline, and the
unseen classes' share of a trained model's NVA.

The oracle (``ovgaussian.bench.baselines.GroundTruthPredictor``) encodes each Gaussian as the one-hot vector of its
stored top-100 label, so its 2D scores say how much the rendering path (blend weights, alpha threshold, argmax
of blended vectors) loses against the stored label maps. With a bench report (``ovgaussian bench --out REPORT``), it also prints
``ovgaussian.metrics.unseen_share`` of the report's NVA confusion matrix.

    .venv/bin/python benchmarks/nva_oracle.py out/bench-suite/dataset
    .venv/bin/python benchmarks/nva_oracle.py out/bench-suite/dataset --report out/bench-suite/reports/table1-02.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ovgaussian.bench.baselines import GroundTruthPredictor  # noqa: E402
from ovgaussian.bench.evaluate import run_bench  # noqa: E402
from ovgaussian.bench.config import BenchConfig  # noqa: E402
from ovgaussian.suite.report import report_unseen_share  # noqa: E402


def _pct(value: float | None) -> float | None:
    return None if value is None else round(100 * value, 2)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="dataset folder (splits train/val)")
    parser.add_argument("--max-views", type=int, default=4, help="views per scene, as the profile (4)")
    parser.add_argument("--report", type=Path, help="a bench report whose NVA is split into the unseen share")
    args = parser.parse_args(argv)
    config = BenchConfig(dataset=args.dataset, metrics=("CSA", "NVA"), dims=("2d",), max_views_per_scene=args.max_views)
    result = run_bench(config, GroundTruthPredictor()).result
    out = {f"oracle 2D {metric}": _pct(result.results[("2d", metric)].scores.miou) for metric in ("CSA", "NVA")}
    if args.report is not None:
        share = report_unseen_share(json.loads(args.report.read_text()))
        if share is None:
            raise SystemExit(f"{args.report}: no NVA confusion matrix (train_2d) in this report")
        out.update({f"report NVA {field}": _pct(value) for field, value in share._asdict().items()})
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
