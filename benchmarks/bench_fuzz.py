"""Benchmark: the full seeded fuzz campaign of the splat readers (counts per verdict and per mutator).

    .venv/bin/python benchmarks/bench_fuzz.py [--mutants 20000] [--seed 18] [--out benchmarks/results/fuzz.md]

Seeds: the real PLYs in ../shared/realdata (or $SEGGAUSSIAN_SHARED/realdata) and files our writer makes
(``seggaussian.tools.fuzz.ply.ply_target``). Every mutant is classified as accepted-and-finite, clean error,
non-finite, crash or hang; the run fails (exit 1) on any crash, hang or non-finite acceptance. CI runs
1,600 of the same mutants in tests/seggaussian/tools/test_fuzz.py.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path


def realdata() -> Path | None:
    """``$SEGGAUSSIAN_SHARED/realdata`` when the variable is set, else ``../shared/realdata`` beside the checkout."""
    shared = os.environ.get("SEGGAUSSIAN_SHARED")
    candidate = (Path(shared) if shared else Path(__file__).resolve().parents[1].parent / "shared") / "realdata"
    return candidate if candidate.is_dir() else None


def main() -> int:
    from seggaussian.tools.fuzz import engine as fuzz
    from seggaussian.tools.fuzz import ply as fuzz_ply
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mutants", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=18)
    parser.add_argument("--timeout", type=float, default=fuzz.DEFAULT_TIMEOUT_S, help="per-mutant limit (s)")
    parser.add_argument("--out", type=Path, default=None, help="also write the Markdown table here")
    args = parser.parse_args()

    root = realdata()
    real = sorted(root.glob("*.ply")) if root else []
    target = fuzz_ply.ply_target(real)
    start, start_cpu = time.perf_counter(), time.process_time()
    with tempfile.TemporaryDirectory() as work:
        report = fuzz.run_fuzz(target, args.mutants, args.seed, Path(work), timeout_s=args.timeout)
    wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    command = " ".join(["benchmarks/bench_fuzz.py", *sys.argv[1:]])
    lines = [
        f"# Fuzz campaign: {target.name} reader", "",
        f"Measured by `.venv/bin/python {command}` on {platform.node() or 'this machine'} "
        f"({os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}); {wall:.1f} s wall, {cpu:.1f} s CPU.", "",
        "Seeds: " + ", ".join(name for name, _ in target.seeds) + ".", "",
        fuzz.format_report(report), "",
        fuzz.seconds_summary(report) + ".", "",
    ]
    failures = report.failures()
    lines += [f"- {o.verdict}: {o.name}: {o.detail}" for o in failures[:50]]
    text = "\n".join(lines).rstrip() + "\n"
    print(text)
    if args.out is not None:
        from seggaussian.util.atomic import write_text_atomic

        write_text_atomic(args.out, text)
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
