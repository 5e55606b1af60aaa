"""Benchmark: SPZ decode of this checkout against the SPZ reader of another git revision, interleaved.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_spz_ab.py [--against main] [--gaussians 1000000]
        [--repeats 5]

On a shared machine two separate runs are not comparable; this one decodes the same files with both
readers in one process, alternating, and prints the median wall and process CPU time of each. The other
revision's ``seggaussian/io/spz.py`` is taken with ``git show REV:...`` and loaded beside ours (it uses the
same helper modules of this checkout; an ``io`` module it imports that this checkout no longer has is loaded
from that revision too, and its third-party imports must be installed: a revision before the libdeflate
change needs ``pip install isal``). Both decodes must be bit-identical, or the script stops.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main() -> None:
    from bench_formats import _gaussians

    from seggaussian.io import spz as ours

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="main", help="git revision whose SPZ reader is compared")
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--sh-degree", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    def load(rev_path: str, name: str):
        source = subprocess.run(["git", "-C", str(ROOT), "show", f"{args.against}:{rev_path}"],
                                capture_output=True, text=True, check=True).stdout
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"{name.rsplit('.', 1)[-1]}.py"
            path.write_text(source)
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules.setdefault(name, module)
            spec.loader.exec_module(module)
        return module

    listing = subprocess.run(["git", "-C", str(ROOT), "ls-tree", "--name-only", args.against, "seggaussian/io/"],
                             capture_output=True, text=True, check=True).stdout.split()
    for rev_path in listing:                   # io modules of that revision that this checkout no longer has
        if rev_path.endswith(".py") and not (ROOT / rev_path).exists():
            load(rev_path, "seggaussian.io." + Path(rev_path).stem)
    other = load("seggaussian/io/spz.py", "spz_other")
    g = _gaussians(args.gaussians, args.sh_degree)
    print(f"{args.gaussians} Gaussians, SH degree {args.sh_degree}; median of {args.repeats}, interleaved")
    for version in (2, 3, 4):
        data = ours.encode_spz(g, version)
        a, b = other.decode_spz(data), ours.decode_spz(data)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            if not np.array_equal(getattr(a, name), getattr(b, name)):
                raise SystemExit(f"SPZ v{version}: the two readers decode '{name}' differently")
        del a, b
        times = {args.against: ([], []), "this checkout": ([], [])}
        for _ in range(args.repeats):
            for label, module in ((args.against, other), ("this checkout", ours)):
                wall, cpu = time.perf_counter(), time.process_time()
                module.decode_spz(data)
                times[label][0].append(time.perf_counter() - wall)
                times[label][1].append(time.process_time() - cpu)
        mb = len(data) / 1e6
        for label, (walls, cpus) in times.items():
            w, c = statistics.median(walls), statistics.median(cpus)
            print(f"SPZ v{version} {mb:6.1f} MB  {label:14s} wall {w:6.3f} s {mb / w:5.0f} MB/s   "
                  f"cpu {c:6.3f} s {mb / c:5.0f} MB/s")


if __name__ == "__main__":
    main()
