"""Benchmark: reading and writing a 1,000,000-Gaussian SH-3 3DGS PLY (about 248 MB).

    .venv/bin/python benchmarks/bench_ply.py [--num 1000000] [--repeats 3]

Generates the file in a temp dir, then times (medians over ``--repeats``, warm page cache):
our binary reader (raw table; full read_gaussians_ply with Gaussians assembly and validation),
plyfile (the reference), and our writer. Prints MB/s per row.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_seconds(fn, repeats: int) -> tuple[float, float]:
    """Median wall-clock and median CPU (process) seconds; CPU time is the figure to trust under load."""
    walls, cpus = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - start_cpu)
    return statistics.median(walls), statistics.median(cpus)


def main() -> None:
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.io.ply.reader import read_gaussians_ply, read_vertex_table, vertex_table_to_gaussians
    from seggaussian.io.ply.reference import read_vertex_table_plyfile
    from seggaussian.io.ply.writer import write_gaussians_ply

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--skip-plyfile", action="store_true")
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    n = args.num
    g = Gaussians.from_arrays(
        rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 3)) - 4,
        rng.normal(size=n), rng.normal(size=(n, 16, 3)) * 0.1,
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench_sh3.ply"
        write_seconds = _median_seconds(lambda: write_gaussians_ply(path, g), args.repeats)
        size_mb = path.stat().st_size / 1e6
        rows = [("write_gaussians_ply (binary LE, normals)", write_seconds)]
        rows.append(("read_vertex_table (np.fromfile, structured dtype)",
                     _median_seconds(lambda: read_vertex_table(path), args.repeats)))
        rows.append(("read_gaussians_ply (table + Gaussians + validation)",
                     _median_seconds(lambda: read_gaussians_ply(path), args.repeats)))
        big = Path(tmp) / "bench_sh3_be.ply"
        write_gaussians_ply(big, g, endian=">")
        rows.append(("read_gaussians_ply, big-endian file (byte swap + copies)",
                     _median_seconds(lambda: read_gaussians_ply(big), args.repeats)))
        big.unlink()
        if not args.skip_plyfile:
            rows.append(("plyfile PlyData.read (reference, raw table)",
                         _median_seconds(lambda: read_vertex_table_plyfile(path), args.repeats)))
            rows.append(("plyfile + vertex_table_to_gaussians",
                         _median_seconds(lambda: vertex_table_to_gaussians(read_vertex_table_plyfile(path)),
                                         args.repeats)))
        back, _ = read_gaussians_ply(path)
        assert back.sh.tobytes() == g.sh.tobytes(), "round trip changed the values"
        print(f"file: {n} Gaussians, SH degree 3, {size_mb:.1f} MB (warm page cache), median of {args.repeats}")
        print(f"{'operation':56s} {'wall s':>7s} {'MB/s':>6s} {'cpu s':>7s} {'MB/s cpu':>8s}")
        for name, (wall, cpu) in rows:
            print(f"{name:56s} {wall:7.3f} {size_mb / wall:6.0f} {cpu:7.3f} {size_mb / cpu:8.0f}")


if __name__ == "__main__":
    main()
