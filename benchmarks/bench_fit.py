"""PSNR versus CPU time of CPU 3DGS fitting on a profile room (what ``ovgaussian bench-suite`` synthesizes).

Usage:
    NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/bench_fit.py [--preset profile] [--scene 10e8510292]
        [--root /tmp/bench_fit_profile] [--iterations N] [--every 50] [--seed 0] [--threads 1]
        [--out benchmarks/results/fit.md] [--note TEXT]

Synthesizes the profile rooms (``seggaussian synth --scenes 9 --replica-scenes 3 --width 160 --views 16 --seed 0``)
into ``--root`` when it holds none, reads ``--scene`` (default: the ScanNet++ val room), warms the numba kernels
up with a 3-iteration fit (compilation is not counted), then fits once with the preset (``FitConfig.preset``;
``--iterations`` rescales it) and evaluates the novel views (never trained on) every ``--every`` iterations.
Each row: iteration, Gaussians, CPU seconds of the fit so far (``time.process_time``, checkpoint evaluation
excluded), novel-view PSNR / SSIM. Reported: the collapse criterion (in the final half of the schedule the
novel-view PSNR never falls more than 1 dB below its best so far), the returned state (keep-best), its opacity
distribution (min / median / p95) and SH degree.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Largest allowed fall (dB) of the novel-view PSNR below its best so far in the final half of the schedule.
COLLAPSE_DB = 1.0


def collapse_check(rows: list[dict], iterations: int) -> dict:
    """Largest fall of the PSNR below its running best among the rows in the final half of the schedule."""
    best, worst_fall = -1e9, 0.0
    for r in rows:
        if r["iteration"] >= iterations / 2:
            worst_fall = max(worst_fall, best - r["novel_psnr"])
        best = max(best, r["novel_psnr"])
    return {"max_fall_db": worst_fall, "ok": worst_fall <= COLLAPSE_DB}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="profile")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--every", type=int, default=50)
    parser.add_argument("--root", type=Path, default=Path("/tmp/bench_fit_profile"))
    parser.add_argument("--scene", default=None, help="scene id (default: the first ScanNet++ val room)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                        help="override a FitConfig field (repeatable), e.g. --set lambda_depth=0")
    parser.add_argument("--out", type=Path, default=None, help="append the markdown table to this file")
    parser.add_argument("--note", default="", help="free text written above the table (e.g. 'under load')")
    args = parser.parse_args()

    import numpy as np
    import torch

    from seggaussian.fit.optimize import fit_scene, read_source_scene
    from seggaussian.fit.config import FitConfig

    torch.set_num_threads(args.threads)
    if not (args.root / "scannetpp" / "data").is_dir():
        subprocess.run([str(Path(sys.executable).with_name("seggaussian")), "synth", "--out", str(args.root), "--scenes",
                        "9", "--replica-scenes", "3", "--width", "160", "--views", "16", "--seed", "0"], check=True)
    scene_id = args.scene or (args.root / "scannetpp" / "splits" / "nvs_sem_val.txt").read_text().split()[0]
    scene = read_source_scene("synthetic", args.root, scene_id)

    config = FitConfig.preset(args.preset)
    if args.iterations:
        config = config.with_iterations(args.iterations)
    config = replace(config, **{k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)})
    fit_scene(scene, replace(config, iterations=3, eval_every=0, lambda_depth=0.0), seed=args.seed, progress=False)
    torch.set_num_threads(args.threads)  # numba's first parallel call may reset torch's thread count

    rows, eval_cpu = [], [0.0]
    cpu0 = time.process_time()

    def on_iteration(p):
        if p.iteration % args.every == 0 or p.iteration == config.iterations:
            t = time.process_time()
            m = p.evaluate_novel()
            rows.append({"iteration": p.iteration, "gaussians": p.num_gaussians,
                         "cpu_seconds": t - cpu0 - eval_cpu[0], "novel_psnr": m["psnr"], "novel_ssim": m["ssim"]})
            eval_cpu[0] += time.process_time() - t
            print(json.dumps(rows[-1]), flush=True)

    load_start = os.getloadavg()[0]
    uptime_start = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    wall0 = time.perf_counter()
    result = fit_scene(scene, config, seed=args.seed, progress=False, on_iteration=on_iteration)
    cpu_total = time.process_time() - cpu0 - eval_cpu[0]
    wall = time.perf_counter() - wall0
    m, g = result.metrics, result.gaussians
    opacity = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    collapse = collapse_check(rows, config.iterations)

    env = f"NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']} " if "NUMBA_NUM_THREADS" in os.environ else ""
    script = Path(sys.argv[0]).resolve()
    repo = Path(__file__).resolve().parents[1]
    script_text = script.relative_to(repo).as_posix() if script.is_relative_to(repo) else script.name
    command = f"{env}.venv/bin/python " + shlex.join([script_text] + sys.argv[1:])
    lines = [
        f"### CPU 3DGS fitting, profile room {scene.scene_id}, preset `{args.preset}` "
        f"({m['image_size'][0]}x{m['image_size'][1]}, {m['train_views']} train / {m['novel_views']} novel views, "
        f"{m['depth_views']} with mesh depth)",
        "",
        f"{args.note}".strip(),
        "",
        f"Command: `{command}`  ",
        f"Machine: {platform.machine()}, {os.cpu_count()} logical CPUs, torch threads {args.threads}, "
        f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'unset')}; `uptime` at start: `{uptime_start}`, "
        f"load average at end {os.getloadavg()[0]:.2f} (start {load_start:.2f}).  ",
        f"Fit: {m['iterations']} iterations, **{cpu_total:.1f} s CPU** (process time, checkpoint evaluation "
        f"excluded; {wall:.1f} s wall incl. evaluation), returned state of iteration {m['returned_iteration']} "
        f"(best held-out PSNR {m['best_heldout_psnr']:.2f} dB): **novel PSNR {m['novel_psnr']:.2f} dB**, SSIM "
        f"{m['novel_ssim']:.3f}; {m['gaussians']} Gaussians, SH degree {g.sh_degree} (active "
        f"{m['active_sh_degree']}), opacity min / median / p95 {opacity.min():.3f} / {np.median(opacity):.3f} / "
        f"{np.percentile(opacity, 95):.3f}.  ",
        f"Collapse criterion (final half: never > {COLLAPSE_DB:g} dB below the best so far): largest fall "
        f"{collapse['max_fall_db']:.2f} dB, {'PASS' if collapse['ok'] else 'FAIL'}.",
        "",
        "| iterations | Gaussians | CPU seconds (fitting) | novel-view PSNR (dB) | novel-view SSIM |",
        "|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| {r['iteration']} | {r['gaussians']} | {r['cpu_seconds']:.1f} | {r['novel_psnr']:.2f} | "
              f"{r['novel_ssim']:.3f} |" for r in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "a") as f:
            f.write("\n" + text)


if __name__ == "__main__":
    main()
