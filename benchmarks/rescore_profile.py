"""Benchmark: score a finished benchmark profile's runs again on its rooms as the current build labels them, without
retraining (what a change of the label transfer alone does to Table 1 and to the 90 % check).

The profile's datasets are rebuilt in place by its own ``build_data`` (fits, oracle samples and whatever else is
unchanged come from the build cache; a changed stage and the stages after it run again), then each named run is
scored by the profile's ``bench_config`` on the dataset it was trained on (its ``RunSpec.trained_on``: the
fitted splats or the oracle Gaussians), and ``full`` against ``full-oracle`` by ``paired_csa_ratio``. Work on a
copy of the profile folder (``cp -a OUT COPY``) to keep the original labels.

    .venv/bin/python benchmarks/rescore_profile.py --out COPY [--runs full full-oracle] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="a finished `ovgaussian bench-suite --out` folder")
    parser.add_argument("--runs", nargs="+", default=["full", "full-oracle"])
    parser.add_argument("--json", type=Path, help="write every run's metrics here")
    args = parser.parse_args()

    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.suite import profile
    from ovgaussian.suite.config import RUNS, SuiteConfig
    from ovgaussian.suite.report import paired_csa_ratio

    trained_on = {spec.name: spec.trained_on for spec in RUNS if spec.trained_on in ("splats", "oracle")}
    unknown = [name for name in args.runs if name not in trained_on]
    if unknown or not (args.out / "runs").is_dir():
        parser.error(f"{args.out}: not a finished profile folder, or runs not of the profile: {unknown}")
    config = SuiteConfig(out=args.out)
    start = time.perf_counter()
    data = profile.build_data(config)
    print(f"datasets rebuilt in {time.perf_counter() - start:.0f} s", flush=True)
    payloads = {}
    for name in args.runs:
        dataset = data.oracle if trained_on[name] == "oracle" else data.splats
        payloads[name] = run_bench(profile.bench_config(config, dataset, run=profile.run_dir(config, name))).payload
        metrics = payloads[name]["metrics"]
        row = " / ".join(f"{dim} {metric} {100 * value['miou']:.1f}" for dim in metrics
                         for metric, value in metrics[dim].items() if value.get("miou") is not None)
        print(f"{name}: {row}", flush=True)
    if {"full", "full-oracle"} <= set(payloads):
        ratio = paired_csa_ratio(payloads["full"], payloads["full-oracle"])
        if ratio is not None:
            print(f"90 % check: full / full-oracle 3D CSA {100 * ratio.value:.1f} % "
                  f"[{100 * ratio.low:.1f}, {100 * ratio.high:.1f}] over {ratio.scenes} val rooms")
    if args.json is not None:
        args.json.write_text(json.dumps({name: p["metrics"] for name, p in payloads.items()}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
