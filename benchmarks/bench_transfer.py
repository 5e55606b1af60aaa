"""Label transfer speed: ``transfer_labels`` against the bare KD-tree (build + query) in the same run.

    .venv/bin/python benchmarks/bench_transfer.py --gaussians 1000000 --points 1000000 --repeats 3

Reports medians of interleaved repeats (run-to-run noise on shared VMs is 15-30 %), the ratio
transfer / bare (target <= 1.3), both backends (scipy cKDTree, open3d), and the peak RSS.
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", default="scipy,open3d")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    from scipy.spatial import cKDTree

    from seggaussian.labels.config import TransferConfig
    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.labels.transfer import transfer_labels

    rng = np.random.default_rng(0)
    # points on the surfaces of a 6 x 5 x 3 m room-sized box (a scan-like 2-manifold), Gaussians near them
    points = rng.uniform([0, 0, 0], [6, 5, 3], (args.points, 3))
    face = rng.integers(0, 3, args.points)
    points[np.arange(args.points), face] = np.where(rng.random(args.points) < 0.5, 0.0, [6, 5, 3][0])
    points[face == 1, 1] = np.where(rng.random((face == 1).sum()) < 0.5, 0.0, 5.0)
    points[face == 2, 2] = np.where(rng.random((face == 2).sum()) < 0.5, 0.0, 3.0)
    semantic = rng.integers(0, 100, args.points).astype(np.int32)
    semantic[rng.random(args.points) < 0.05] = IGNORE_LABEL
    instance = rng.integers(0, 500, args.points).astype(np.int32)
    means = points[rng.integers(0, args.points, args.gaussians)] + rng.normal(0, 0.01, (args.gaussians, 3))
    labelled = points[semantic != IGNORE_LABEL]

    results: dict[str, list[float]] = {}

    def timed(name, fn):
        t = time.perf_counter()
        fn()
        results.setdefault(name, []).append(time.perf_counter() - t)

    backends = [b for b in args.backends.split(",") if b]
    for _ in range(args.repeats):
        timed("bare cKDTree build+query (labelled points)", lambda: cKDTree(labelled).query(means, workers=-1))
        for backend in backends:
            if backend == "open3d":
                import open3d as o3d

                def bare_o3d():
                    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(labelled))
                    nns.knn_index()
                    nns.knn_search(o3d.core.Tensor(means), 1)

                timed("bare open3d build+query (labelled points)", bare_o3d)
            timed(f"transfer_labels backend={backend}",
                  lambda b=backend: transfer_labels(means, points, semantic, instance, None, TransferConfig(backend=b)))
    med = {k: float(np.median(v)) for k, v in results.items()}
    bare = med["bare cKDTree build+query (labelled points)"]
    ratio = {k: v / bare for k, v in med.items()}
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    payload = {"gaussians": args.gaussians, "points": args.points, "repeats": args.repeats,
               "median_seconds": med, "ratio_to_bare_ckdtree": ratio, "peak_rss_gb": peak_gb}
    if args.json:
        print(json.dumps(payload, indent=2))
        return
    for k in med:
        print(f"{k:48s} {med[k]:7.3f} s   x{ratio[k]:.2f}   (runs: {', '.join(f'{t:.2f}' for t in results[k])})")
    print(f"peak RSS {peak_gb:.2f} GB")


if __name__ == "__main__":
    main()
