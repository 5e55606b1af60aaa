"""Benchmark: does a fit end near its best? Held-out PSNR at the end of each fit against its best, per preset.

A fit keeps its best evaluated state (``FitConfig.keep_best``), but a run whose end falls far below its best wasted
the rest of its budget (an opacity reset it never recovered from). For every room of a raw tree (``seggaussian
synth``) and every preset asked for, this fits the room (``seggaussian.fit.optimize.fit_scene``, seed 0, the preset's
own schedule, or under ``--time-budget`` seconds) and reports the best and the final held-out PSNR, the opacity
resets done and skipped, and whether the end is within ``--max-drop`` dB of the best. Exit status 1 if a fit is not.

    .venv/bin/python benchmarks/fit_end_vs_best.py --raw out/demo/raw --preset profile --preset default \\
        --time-budget default=90 --jobs 2 --out out/fit_end_vs_best.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def fit_one(raw: str, scene_id: str, preset: str, budget: float) -> dict:
    import torch
    from dataclasses import replace

    from seggaussian.fit.config import FitConfig
    from seggaussian.fit.optimize import fit_scene, read_source_scene

    torch.set_num_threads(1)  # one fit per core
    config = FitConfig.preset(preset)
    if budget:
        config = replace(config, time_budget_seconds=budget)
    result = fit_scene(read_source_scene("synthetic", raw, scene_id), config, seed=0, progress=False)
    m = result.metrics
    return {"scene": scene_id, "preset": preset, "budget_s": budget, "best": m["best_heldout_psnr"],
            "final": m["final_heldout_psnr"], "iterations": m["iterations"], "gaussians": m["gaussians"],
            "resets": m["opacity_resets"], "skipped_resets": m["skipped_opacity_resets"], "seconds": m["seconds"],
            "history": [(h["iteration"], h["heldout_psnr"]) for h in result.history]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--raw", type=Path, required=True)
    parser.add_argument("--preset", action="append", required=True, choices=["default", "profile"])
    parser.add_argument("--time-budget", action="append", default=[], help="PRESET=SECONDS, repeatable")
    parser.add_argument("--max-drop", type=float, default=1.0, help="dB the end may fall below the best")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    from seggaussian.sources.layout import layout_roots, reader
    from seggaussian.util.workers import pool_options

    budgets = {k: float(v) for k, v in (item.split("=", 1) for item in args.time_budget)}
    scenes = [s for domain, root in layout_roots("synthetic", args.raw)
              for s in sorted(reader(domain).list_scenes(root))]
    jobs = [(str(args.raw), s, p, budgets.get(p, 0.0)) for p in args.preset for s in scenes]
    with ProcessPoolExecutor(max_workers=args.jobs, **pool_options(multiprocessing.get_context("spawn"))) as pool:
        rows = list(pool.map(fit_one, *zip(*jobs)))
    print("| preset | budget (s) | room | iterations | Gaussians | best (dB) | end (dB) | drop (dB) | resets "
          "| skipped |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---|---|")
    failed = 0
    for r in rows:
        drop = r["best"] - r["final"] if r["final"] is not None else 0.0
        r["drop"] = drop
        failed += drop > args.max_drop
        print(f"| {r['preset']} | {r['budget_s']:g} | {r['scene']} | {r['iterations']} | {r['gaussians']:,} | "
              f"{r['best']:.2f} | {r['final']:.2f} | {drop:.2f} | {r['resets']} | {r['skipped_resets']} |")
    for preset in args.preset:
        drops = [r["drop"] for r in rows if r["preset"] == preset]
        print(f"\n{preset}: largest drop {max(drops):.2f} dB over {len(drops)} rooms "
              f"({sum(d > args.max_drop for d in drops)} beyond {args.max_drop} dB)")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
