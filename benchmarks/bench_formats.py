"""Benchmark: decode speed of every splat format on a >= 100 MB file of each.

    .venv/bin/python benchmarks/bench_formats.py [--mb 110] [--repeats 3] [--sh-degree 3]

For each format the script writes random Gaussians (SH degree ``--sh-degree``) with our writer until the
file holds at least ``--mb`` MB, then times, with a warm page cache (medians over ``--repeats``):

* ``decode``: ``io.formats.read_gaussians_raw`` (file -> Gaussians; for SPZ including gunzip / zstd);
* ``read``: ``io.formats.read_gaussians`` (content detection + decode + validation), what every command runs.

MB/s is file bytes per second; for SPZ the decompressed payload rate is printed too. Process CPU time
is printed beside the wall time: the machine is shared, CPU time is the figure to trust under load.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_seconds(fn, repeats: int) -> tuple[float, float]:
    walls, cpus = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - start_cpu)
    return statistics.median(walls), statistics.median(cpus)


def _gaussians(n: int, degree: int, seed: int = 0):
    from seggaussian.core.gaussians import Gaussians

    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians.from_arrays(
        rng.uniform(-50, 50, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-8, 1, (n, 3)), rng.normal(0, 3, n),
        np.concatenate([rng.uniform(-1.5, 1.5, (n, 1, 3)), rng.uniform(-0.8, 0.8, (n, k - 1, 3))], axis=1),
    )


def main() -> None:
    from seggaussian.io.formats import read_gaussians, read_gaussians_raw, write_gaussians

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", type=float, default=110.0, help="Minimum file size per format (MB).")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sh-degree", type=int, default=3)
    parser.add_argument("--formats", default="ply,compressed_ply,splat,spz2,spz3,spz4,ksplat0,ksplat1,ksplat2")
    args = parser.parse_args()

    # bytes per Gaussian of each format (SPZ: uncompressed payload; the file size is measured after writing)
    k = (args.sh_degree + 1) ** 2
    k_ksplat = (min(args.sh_degree, 2) + 1) ** 2          # the .ksplat writer stops at degree 2 (GaussianSplats3D)
    per_gaussian = {"ply": 4 * (17 + 3 * (k - 1)), "compressed_ply": 16 + 3 * (k - 1), "splat": 32,
                    "spz2": 19 + 3 * (k - 1), "spz3": 20 + 3 * (k - 1), "spz4": 20 + 3 * (k - 1),
                    "ksplat0": 44 + 12 * (k_ksplat - 1), "ksplat1": 24 + 6 * (k_ksplat - 1),
                    "ksplat2": 24 + 3 * (k_ksplat - 1)}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.formats.split(","):
            fmt = "spz" if name.startswith("spz") else "ksplat" if name.startswith("ksplat") else name
            degree = 0 if name == "splat" else min(args.sh_degree, 2) if fmt == "ksplat" else args.sh_degree
            n = int(args.mb * 1e6 / per_gaussian[name]) + 1
            path = Path(tmp) / f"bench_{name}.bin"
            while True:
                g = _gaussians(n, degree)
                options = ({"spz_version": int(name[3])} if fmt == "spz" else
                           {"ksplat_level": int(name[6])} if fmt == "ksplat" else {})
                write_gaussians(path, g, fmt, **options)
                size_mb = path.stat().st_size / 1e6
                if size_mb >= args.mb:
                    break
                n = int(n * args.mb / size_mb * 1.02) + 1
            del g
            decode = _median_seconds(lambda: read_gaussians_raw(path), args.repeats)
            full = _median_seconds(lambda: read_gaussians(path), args.repeats)
            payload_mb = n * per_gaussian[name] / 1e6
            rows.append((name, n, degree, size_mb, payload_mb, decode, full))
            path.unlink()
    print(f"warm page cache, median of {args.repeats}; MB/s = file bytes per second")
    print(f"{'format':15s} {'gaussians':>10s} {'SH':>2s} {'file MB':>8s} | {'decode s':>8s} {'MB/s':>6s} "
          f"{'cpu s':>6s} {'MB/s cpu':>8s} | {'read s':>7s} {'MB/s':>6s} {'MB/s cpu':>8s} | payload MB/s (decode)")
    for name, n, degree, size_mb, payload_mb, (dw, dc), (fw, fc) in rows:
        print(f"{name:15s} {n:10d} {degree:2d} {size_mb:8.1f} | {dw:8.3f} {size_mb / dw:6.0f} {dc:6.3f} "
              f"{size_mb / dc:8.0f} | {fw:7.3f} {size_mb / fw:6.0f} {size_mb / fc:8.0f} | {payload_mb / dw:6.0f}")


if __name__ == "__main__":
    main()
