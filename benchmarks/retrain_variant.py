"""Retrain a finished run with other input settings, everything else equal, and bench it as an earlier report did.

Issue 27's comparison of the input encoding, the voxel pooling, the class weights (``--class-balance``) and the
voxel size (``--voxel-size``) and the Lovasz-softmax term (``--lovasz-weight``) on fitted splats, and issue 31's learning check of a 3D-loss subset
(``--loss-gaussians``): the run's config.json is read back through ``config_from_dict``, only the named settings
change, and the bench uses the report's own BenchConfig (same dataset, splits, classes, views), so the two reports
differ only by the setting.

    .venv/bin/python benchmarks/retrain_variant.py --run out/suite-fit20/runs/full \\
        --report out/suite-fit20/reports/table1-02.json --out out/variants/raw-mean \\
        --input-encoding raw --pool-weighting mean
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="finished run folder whose config.json is retrained")
    parser.add_argument("--report", type=Path, required=True, help="bench report (JSON) whose BenchConfig is reused")
    parser.add_argument("--out", type=Path, required=True, help="new run folder; the report goes to OUT/report.json")
    parser.add_argument("--input-encoding", choices=("raw", "robust"), default=None)
    parser.add_argument("--pool-weighting", choices=("mean", "opacity"), default=None)
    parser.add_argument("--devoxelize", choices=("nearest", "trilinear"), default=None)
    parser.add_argument("--voxel-geometry", action=argparse.BooleanOptionalAction, default=None,
                        help="give the backbone the centres' offset and covariance in each voxel")
    parser.add_argument("--seed", type=int, default=None,
                        help="override the run's seed (network initialization, scene order, sampling): the "
                             "run-to-run spread")
    parser.add_argument("--epochs", type=int, default=None, help="override the run's epochs (a quick check)")
    parser.add_argument("--voxel-size", type=float, default=None, help="voxel edge (m) of the network's finest level")
    parser.add_argument("--loss-gaussians", type=int, default=None,
                        help="Gaussians per scene in the 3D-to-text loss (DataConfig.loss_gaussians)")
    parser.add_argument("--class-balance", type=float, default=None,
                        help="exponent of the class weights of the text cross-entropies (LossConfig.class_balance)")
    parser.add_argument("--opacity-power", type=float, default=None,
                        help="exponent of the opacity weights of the 3D-to-text cross-entropy (LossConfig.opacity_power)")
    parser.add_argument("--lovasz-weight", type=float, default=None,
                        help="weight of the Lovasz-softmax term of the 3D-to-text loss (LossConfig.lovasz_weight)")
    args = parser.parse_args()

    from ovgaussian.bench.config import BenchConfig
    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.run.config import TrainConfig, config_from_dict
    from ovgaussian.train.loop import train
    from seggaussian.util.atomic import write_json_atomic

    saved = config_from_dict(TrainConfig, json.loads((args.run / "config.json").read_text())["train"])
    changes = {k: v for k, v in (("input_encoding", args.input_encoding), ("pool_weighting", args.pool_weighting),
                                 ("devoxelize", args.devoxelize), ("seed", args.seed), ("epochs", args.epochs),
                                 ("voxel_size", args.voxel_size), ("voxel_geometry", args.voxel_geometry))
               if v is not None}
    config = dataclasses.replace(saved, out=args.out / "run", progress=False, **changes)
    if args.loss_gaussians is not None:
        config = dataclasses.replace(config, data=dataclasses.replace(config.data, loss_gaussians=args.loss_gaussians))
        changes["loss_gaussians"] = args.loss_gaussians
    if args.class_balance is not None:
        config = dataclasses.replace(config, loss=dataclasses.replace(config.loss, class_balance=args.class_balance))
        changes["class_balance"] = args.class_balance
    if args.lovasz_weight is not None:
        config = dataclasses.replace(config, loss=dataclasses.replace(config.loss, lovasz_weight=args.lovasz_weight))
        changes["lovasz_weight"] = args.lovasz_weight
    if args.opacity_power is not None:
        config = dataclasses.replace(config, loss=dataclasses.replace(config.loss, opacity_power=args.opacity_power))
        changes["opacity_power"] = args.opacity_power
    started = time.perf_counter()
    result = train(config)
    trained_s = time.perf_counter() - started
    bench_payload = json.loads(args.report.read_text())["config"]
    bench = config_from_dict(BenchConfig, {**bench_payload, "run": str(args.out / "run"), "checkpoint": None})
    report = run_bench(bench)
    write_json_atomic(args.out / "report.json", {**report.payload, "variant": changes, "train_s": trained_s})
    print(report.row)
    print(f"variant {changes}: {result.steps} steps in {trained_s:.0f} s -> {args.out / 'report.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
