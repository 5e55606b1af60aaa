"""PSNR versus wall time of CPU 3DGS fitting on the default synthetic room (320x240).

Usage:
    .venv/bin/python benchmarks/bench_fit.py [--iterations 3000] [--checkpoints 250,500,1000,2000,3000]
        [--root /tmp/bench_fit_synth] [--seed 0] [--threads 2] [--out benchmarks/results/fit.md]

Synthesizes the default synthetic room (ScanNet++ layout, seed 0, scene 0) when ``--root`` holds none,
then fits it once with the default FitConfig (early stop off so that every checkpoint is reached) and
evaluates the novel views (every 8th view, never trained on) at each checkpoint. Each row: iteration,
Gaussians, fitting seconds so far (evaluation time excluded), novel-view PSNR and SSIM.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=3000)
    parser.add_argument("--checkpoints", default="100,250,500,1000,1500,2000,3000")
    parser.add_argument("--root", type=Path, default=Path("/tmp/bench_fit_synth"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--downscale", type=float, default=1.0)
    parser.add_argument("--max-gaussians", type=int, default=None)
    parser.add_argument("--out", type=Path, default=None, help="append the markdown table to this file")
    parser.add_argument("--note", default="", help="free text written above the table (e.g. 'under load')")
    args = parser.parse_args()

    import torch

    from seggaussian.fit import fit_scene
    from seggaussian.fit_config import FitConfig
    from seggaussian.sources import scannetpp, synthetic

    torch.set_num_threads(args.threads)
    ids = scannetpp.list_scenes(args.root) if (args.root / "data").is_dir() else []
    if not ids:
        ids = synthetic.synthesize(args.root, 1, 0, "scannetpp")
    scene = scannetpp.read_scene(args.root, ids[0])

    checkpoints = sorted({int(c) for c in args.checkpoints.split(",") if int(c) <= args.iterations} | {args.iterations})
    config = FitConfig().with_iterations(args.iterations)  # the default schedule, scaled to the run length
    config = replace(config, patience=0, eval_every=0, downscale=args.downscale)
    if args.max_gaussians:
        config = replace(config, max_gaussians=args.max_gaussians)
    rows = []
    eval_seconds = [0.0]

    def on_iteration(p):
        if p.iteration == 1:  # numba's first parallel call resets torch's thread count: set it again
            torch.set_num_threads(args.threads)
        if p.iteration in checkpoints:
            t = time.perf_counter()
            m = p.evaluate_novel()
            rows.append({"iteration": p.iteration, "gaussians": p.num_gaussians, "seconds": p.seconds - eval_seconds[0],
                         "novel_psnr": m["psnr"], "novel_ssim": m["ssim"]})
            eval_seconds[0] += time.perf_counter() - t
            print(json.dumps(rows[-1]), flush=True)

    load_start = os.getloadavg()[0]
    start = time.perf_counter()
    result = fit_scene(scene, config, seed=args.seed, progress=True, on_iteration=on_iteration)
    total = time.perf_counter() - start

    env = f"NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']} " if "NUMBA_NUM_THREADS" in os.environ else ""
    command = f"{env}.venv/bin/python " + shlex.join([Path(sys.argv[0]).as_posix()] + sys.argv[1:])
    lines = [
        f"### CPU 3DGS fitting, default synthetic room {scene.scene_id} "
        f"({result.metrics['image_size'][0]}x{result.metrics['image_size'][1]}, "
        f"{result.metrics['train_views']} train / {result.metrics['novel_views']} novel views)",
        "",
        f"{args.note}".strip(),
        "",
        f"Command: `{command}`  ",
        f"Machine: {platform.machine()}, {os.cpu_count()} logical CPUs, torch threads {args.threads}, "
        f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'unset')}, "
        f"load average at start {load_start:.1f}, at end {os.getloadavg()[0]:.1f}. Total wall time {total:.1f} s "
        f"(including {eval_seconds[0]:.1f} s of checkpoint evaluation). Final: {result.metrics['gaussians']} Gaussians, "
        f"novel PSNR {result.metrics['novel_psnr']:.2f} dB, SSIM {result.metrics['novel_ssim']:.3f}.",
        "",
        "| iterations | Gaussians | seconds (fitting) | novel-view PSNR (dB) | novel-view SSIM |",
        "|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| {r['iteration']} | {r['gaussians']} | {r['seconds']:.1f} | {r['novel_psnr']:.2f} | "
              f"{r['novel_ssim']:.3f} |" for r in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "a") as f:
            f.write("\n" + text)


if __name__ == "__main__":
    main()
