"""Training step of the benchmark profile's ``full`` run on a built profile dataset, per 3D-loss subset size.

Each setting trains the profile's ``full`` TrainConfig (``ovgaussian.suite.profile.train_config``) for ``--epochs``
epochs in a fresh subprocess, one torch and numba thread (as ``bench-suite`` trains), into a temporary folder,
and reports the median and mean wall time and the median CPU time of ``train_step`` over the steps after the
first epoch (the first reads and prepares the rooms), timed by ``bench_train_threads.time_training``. Every
setting draws the same batches (same seed).

    .venv/bin/python benchmarks/bench_profile_step.py --dataset OUT/dataset --loss-gaussians 0 15000
    .venv/bin/python benchmarks/bench_profile_step.py --dataset OUT/dataset-oracle --loss-gaussians 0 15000
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def one(dataset: Path, loss_gaussians: int, epochs: int) -> dict:
    """Train the profile's ``full`` run with this subset (0: every Gaussian), one thread: step times after epoch 1
    (``bench_train_threads.time_training``)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_train_threads import time_training

    from ovgaussian.suite import profile
    from ovgaussian.suite.config import RUNS, SuiteConfig

    with tempfile.TemporaryDirectory(prefix="bench-profile-step-") as folder:
        suite = SuiteConfig(out=Path(folder), epochs=epochs, loss_gaussians=loss_gaussians or None)
        spec = next(r for r in RUNS if r.name == "full")
        run = replace(profile.train_config(suite, spec, dataset), threads=1)
        return {"loss_gaussians": loss_gaussians, **time_training(run, warmup_steps=None)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True, help="a profile dataset (OUT/dataset or "
                        "OUT/dataset-oracle of `ovgaussian bench-suite`)")
    parser.add_argument("--loss-gaussians", type=int, nargs="+", default=[0, 15000],
                        help="subset sizes to time (0: every Gaussian)")
    parser.add_argument("--epochs", type=int, default=2, help="epochs per setting (the first is not timed)")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: one setting, JSON out
    args = parser.parse_args()
    if args.epochs < 2:
        parser.error("--epochs must be at least 2 (the first epoch is not timed)")
    if not args.dataset.is_dir():
        parser.error(f"--dataset {args.dataset}: no such folder")
    if args.one is not None:
        print(json.dumps(one(args.dataset, args.one, args.epochs)))
        return
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    rows = []
    for size in args.loss_gaussians:
        done = subprocess.run([sys.executable, __file__, "--dataset", str(args.dataset), "--epochs", str(args.epochs),
                               "--one", str(size)], env=env, capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"bench_profile_step: --loss-gaussians {size} failed: {done.stderr.strip().splitlines()[-1]}")
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print("| 3D-loss subset | steps timed | median step s | mean step s | median step CPU s |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        label = "every Gaussian" if r["loss_gaussians"] == 0 else f"{r['loss_gaussians']:,}"
        print(f"| {label} | {r['steps']} | {r['step_wall_s']:.2f} | {r['step_wall_mean_s']:.2f} "
              f"| {r['step_cpu_s']:.2f} |")


if __name__ == "__main__":
    main()
