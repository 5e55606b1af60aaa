"""SH colour evaluation, forward + backward: the compiled contraction against two torch formulations, in one run.

    .venv/bin/python benchmarks/bench_sh.py [--gaussians 30000] [--degree 3] [--repeats 21] [--threads 1]

Implementations (all with the same torch ``sh_basis``, differentiable in the directions):
- ``evaluate_sh``: the basis-coefficient contraction in one compiled pass forward and one backward (numba);
- ``broadcast``: ``(basis[..., None] * sh[:, :K]).sum(1)`` in torch;
- ``evaluate_sh_reference``: one coefficient at a time (``sh[:, k]``), as ``evaluate_sh`` was written before: each
  selected coefficient costs autograd a zero-filled ``[N, K, 3]`` gradient.

Each is timed alternated (A B C A B C ...), median wall time of ``--repeats`` calls of forward + ``backward`` of
``sum(out^2)`` into fresh gradients. The default size is a profile-room fit's (30,000 Gaussians, SH degree 3), run at
one thread as the fit runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=30_000)
    parser.add_argument("--degree", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()

    import numba
    import torch

    import seggaussian  # noqa: F401  (passive OpenMP waits, as every command)
    from seggaussian.render.sh import evaluate_sh, evaluate_sh_reference, sh_basis

    torch.set_num_threads(args.threads)
    numba.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    sh = torch.randn(args.gaussians, 16, 3, generator=gen)
    dirs = torch.nn.functional.normalize(torch.randn(args.gaussians, 3, generator=gen), dim=1)
    k = (args.degree + 1) ** 2

    def broadcast(s, d, degree):
        return (sh_basis(d, degree).unsqueeze(-1) * s[:, :k]).sum(1)

    impls = {"evaluate_sh (compiled contraction)": evaluate_sh, "broadcast product (torch)": broadcast,
             "evaluate_sh_reference (per coefficient, torch)": evaluate_sh_reference}
    times: dict[str, list[float]] = {name: [] for name in impls}
    for rep in range(args.repeats + 1):
        for name, fn in impls.items():
            s, d = sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)
            t0 = time.perf_counter()
            fn(s, d, args.degree).square().sum().backward()
            if rep:  # the first round warms up (numba cache load)
                times[name].append(time.perf_counter() - t0)
    print(f"SH degree {args.degree}, {args.gaussians:,} Gaussians, {args.threads} thread(s), forward + backward, "
          f"median of {args.repeats} (alternated):")
    for name, values in times.items():
        print(f"  {name}: {statistics.median(values) * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
