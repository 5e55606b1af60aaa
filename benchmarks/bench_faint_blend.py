"""Benchmark: the faint-Gaussian blend of ``ovgaussian bench/predict --faint-neighbours`` (``ovgaussian.predict.
faint_blend``): its cost per scene, by the scene's size and K (the encoding it follows is not timed here).

Points on the faces of a 6 x 5 x 3 m box room with clutter and floaters (``bench_devoxelize.room_points``),
opacities drawn as a fit leaves them (uniform squared: a third under 0.1), 16-d vectors. Median of ``--reps`` calls
of ``faint_blend`` per size and K, one thread (the k-d tree query is single-threaded). Prints a markdown table.

    .venv/bin/python benchmarks/bench_faint_blend.py --points 150000 1000000 --neighbours 8 16 --reps 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[150000, 1000000])
    parser.add_argument("--neighbours", type=int, nargs="+", default=[8])
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()

    from bench_devoxelize import room_points
    from ovgaussian.predict.faint_blend import faint_blend

    print("| Gaussians | K | faint_blend (median) | per 1,000,000 Gaussians |")
    print("|---:|---:|---:|---:|")
    for n in args.points:
        means = room_points(n, seed=0).numpy().astype(np.float64)
        rng = np.random.default_rng(0)
        opacity = rng.uniform(0, 1, n) ** 2
        vectors = rng.normal(size=(n, 16)).astype(np.float32)
        for k in args.neighbours:
            times = []
            for _ in range(args.reps):
                start = time.perf_counter()
                out = faint_blend(means, opacity, vectors, k)
                times.append(time.perf_counter() - start)
            assert np.isfinite(out).all()
            median = statistics.median(times)
            print(f"| {n:,} | {k} | {median:.2f} s | {median * 1e6 / n:.2f} s |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
