"""Training steps of a real dataset at several thread counts, each in a fresh process, phase by phase.

Why: with passive OpenMP waits (``seggaussian/__init__.py``) every parallel region wakes sleeping threads, and a
small step runs thousands of small regions; ``ovgaussian train`` therefore uses one thread below
``seggaussian.util.threads.PARALLEL_MIN_GAUSSIANS`` Gaussians per step. This measures that choice on a dataset.

Each configuration trains ``--epochs`` epochs with the demo's options (slim, 10 cm voxels, coordinates, 4,096
pixels per view, class balance 0.5, lr 0.05) into a temporary folder; the first two steps are warm-up, the rest are
timed (wall and process CPU), split by phase as in ``bench_paper_step.py``. Configurations alternate when
``--repeats`` > 1.

    .venv/bin/python benchmarks/bench_train_threads.py --data out/demo/dataset            # 1 and 2 threads
    .venv/bin/python benchmarks/bench_train_threads.py --data out/demo/dataset --threads 1 2 --repeats 2
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def time_training(config, warmup_steps: int | None = 2) -> dict:
    """Train ``config`` in this process with every step timed (wall and process CPU) and split by phase as in
    ``bench_paper_step.py``: median step wall/CPU, mean step wall, and mean phase seconds per step over the steps
    after ``warmup_steps`` (None: after the first epoch, whose steps read and prepare the scenes)."""
    sys.path.insert(0, str(REPO))
    sys.path.insert(0, str(REPO / "benchmarks"))
    import seggaussian  # noqa: F401  (first: its OpenMP defaults must be set before torch starts its threads)
    import torch

    import bench_paper_step as paper
    import ovgaussian.train.loop as loop

    timer = paper.PhaseTimer()
    steps: list[tuple[float, float]] = []
    original_step = loop.train_step
    warmup = []

    def timed_step(run, *args):
        if not warmup:
            warmup.append(run.steps_per_epoch if warmup_steps is None else warmup_steps)
            paper.instrument(timer, run.data, run.net)
            backward = torch.Tensor.backward

            def timed_backward(self, *a, **k):
                with timer.measure("backward"):
                    return backward(self, *a, **k)

            torch.Tensor.backward = timed_backward
        t0, c0 = time.perf_counter(), time.process_time()
        result = original_step(run, *args)
        steps.append((time.perf_counter() - t0, time.process_time() - c0))
        if len(steps) == warmup[0]:
            timer.seconds.clear()  # the warm-up steps are not timed
        return result

    loop.train_step = timed_step
    try:
        loop.train(config)
    finally:
        loop.train_step = original_step
    timed = steps[warmup[0]:] if warmup else []
    if not timed:
        raise SystemExit("too few steps: raise --epochs")
    return {"steps": len(timed), "step_wall_s": statistics.median(w for w, _ in timed),
            "step_wall_mean_s": statistics.fmean(w for w, _ in timed),
            "step_cpu_s": statistics.median(c for _, c in timed), "voxels_last_step": getattr(timer, "voxels", None),
            "phases_s_per_step": {p: s / len(timed) for p, s in sorted(timer.seconds.items())}}


def one_run(data: str, threads: int, epochs: int) -> dict:
    """Train in this process (called in a child) with the demo's options: :func:`time_training` after 2 steps."""
    sys.path.insert(0, str(REPO))
    from ovgaussian.run.config import DataConfig, LossConfig, OptimConfig, TrainConfig

    with tempfile.TemporaryDirectory() as out:
        config = TrainConfig(out=Path(out) / "run", epochs=epochs, model_preset="slim", voxel_size=0.1,
                             use_coordinates=True, progress=False, threads=threads,
                             data=DataConfig(dataset=Path(data), num_classes=20, pixels_per_view=4096),
                             loss=LossConfig(class_balance=0.5), optim=OptimConfig(lr=0.05))
        return {"threads": threads, **time_training(config, warmup_steps=2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="dataset folder (e.g. out/demo/dataset from make demo)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts to compare")
    parser.add_argument("--epochs", type=int, default=4, help="epochs per configuration (first 2 steps: warm-up)")
    parser.add_argument("--repeats", type=int, default=1, help="alternating repeats of every configuration")
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # child process: one thread count
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(one_run(args.data, args.one, args.epochs)))
        return 0
    results = []
    for _ in range(args.repeats):
        for threads in args.threads:
            done = subprocess.run([sys.executable, __file__, "--data", args.data, "--epochs", str(args.epochs),
                                   "--one", str(threads)], capture_output=True, text=True, check=False)
            if done.returncode != 0:
                print(done.stderr[-2000:], file=sys.stderr)
                return 1
            results.append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(json.dumps(results[-1]), flush=True)
    print(f"\nmachine: {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f} at the end")
    phases = sorted({p for r in results for p in r["phases_s_per_step"]})
    print("| threads | step wall s | step CPU s | " + " | ".join(phases) + " |")
    print("|---:|---:|---:|" + "---:|" * len(phases))
    for r in results:
        print(f"| {r['threads']} | {r['step_wall_s']:.2f} | {r['step_cpu_s']:.2f} | "
              + " | ".join(f"{r['phases_s_per_step'].get(p, 0.0):.3f}" for p in phases) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
