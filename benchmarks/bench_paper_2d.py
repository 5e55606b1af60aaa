"""The 2D benchmark of one paper-scale scene: 1,000,000 Gaussians, 50 views of 584x876 (issue 17).

Runs ``ovgaussian.bench.evaluate.evaluate`` (2D CSA on the ``val`` split) with the real blend weights, streamed
band by band (``--band-rows``; nothing per pixel cached), and a stand-in predictor: random 16-d
per-Gaussian vectors classified by a fixed random linear map (the time of a trained network's
``encode`` is not part of the 2D evaluation). Prints wall time, process CPU time, time per view and
the peak resident memory; exit status 1 when the peak exceeds ``--max-peak-gb``.

    .venv/bin/python benchmarks/bench_paper_2d.py                      # 1,000,000 Gaussians, 50 views
    .venv/bin/python benchmarks/bench_paper_2d.py --gaussians 100000 --views 5
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


class RandomLinearPredictor:
    """``encode``: seeded random 16-d vectors; ``classify``: a seeded random 16 x K linear map."""

    name = "random-linear"

    def __init__(self, seed: int = 0) -> None:
        import numpy as np

        self.rng_seed = seed
        self.np = np

    def encode(self, scene):
        return self.np.random.default_rng(self.rng_seed).normal(size=(len(scene.gaussians), 16)).astype("float32")

    def classify(self, vectors, class_ids):
        weights = self.np.random.default_rng(self.rng_seed + 1).normal(size=(16, len(class_ids))).astype("float32")
        return vectors @ weights


def compare_render(num_gaussians: int, band_rows: int) -> dict:
    """M = W S of one 584x876 view band by band: ``render.render_features`` (torch, what the bench used) vs
    ``render_features_no_grad`` (compiled), interleaved per band in this process; wall and CPU seconds."""
    import numpy as np
    import torch

    from bench_paper_step import make_room
    from seggaussian.render import render_features
    from seggaussian.render.pixel_blend import ViewBlender, render_features_no_grad
    from seggaussian.render.rasterize import camera_tensors

    scene = make_room(0, num_gaussians, views=1)
    g, cam = scene.gaussians, scene.views[0].camera
    blender = ViewBlender(*(torch.tensor(getattr(g, n)) for n in ("means", "quats", "log_scales", "opacity_logits")),
                          *camera_tensors(cam), cam.width, cam.height, 16)
    vectors = np.random.default_rng(0).normal(size=(len(g), 16)).astype(np.float32)
    totals = {"torch": [0.0, 0.0], "compiled": [0.0, 0.0]}
    render_features_no_grad(np.zeros((1, 16), np.int64), np.zeros((1, 16), np.float32), vectors)  # compile
    for r0 in range(0, cam.height, band_rows):
        band = blender.rows(r0, min(cam.height, r0 + band_rows))
        for name in ("torch", "compiled"):
            t, c = time.perf_counter(), time.process_time()
            if name == "torch":
                with torch.no_grad():
                    out = render_features(band, torch.from_numpy(vectors)).numpy()
            else:
                out = render_features_no_grad(band.ids.numpy(), band.weights.numpy(), vectors)
            totals[name][0] += time.perf_counter() - t
            totals[name][1] += time.process_time() - c
            del out
    return {"gaussians": num_gaussians, "band_rows": band_rows,
            **{f"{k}_wall_s": v[0] for k, v in totals.items()}, **{f"{k}_cpu_s": v[1] for k, v in totals.items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--views", type=int, default=50)
    parser.add_argument("--band-rows", type=int, default=None, help="rows per band (default: the bench's)")
    parser.add_argument("--max-peak-gb", type=float, default=16.0)
    parser.add_argument("--compare-render", action="store_true",
                        help="only compare the torch and compiled M = W S on one view (interleaved per band)")
    args = parser.parse_args()
    if args.compare_render:
        from ovgaussian.predict.config import DEFAULT_BAND_ROWS

        r = compare_render(args.gaussians, args.band_rows or DEFAULT_BAND_ROWS)
        print(json.dumps(r))
        print(f"M = W S of one 584x876 view: torch render_features {r['torch_wall_s']:.2f} s wall / "
              f"{r['torch_cpu_s']:.2f} s CPU, compiled {r['compiled_wall_s']:.2f} s wall / {r['compiled_cpu_s']:.2f} s CPU")
        return 0

    from bench_paper_step import make_room
    from ovgaussian.bench.evaluate import evaluate
    from ovgaussian.text.vocabulary import benchmark_vocabulary
    from ovgaussian.predict.config import DEFAULT_BAND_ROWS

    band_rows = args.band_rows or DEFAULT_BAND_ROWS
    t0 = time.perf_counter()
    scene = make_room(0, args.gaussians, views=args.views)
    scene = scene._replace(views=[v._replace(role="train") for v in scene.views])
    setup_s = time.perf_counter() - t0
    rss_setup = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    done = []
    t1, c1 = time.perf_counter(), time.process_time()
    result = evaluate(RandomLinearPredictor(), {"val": [scene]}, benchmark_vocabulary(20), metrics=("CSA",),
                      dims=("2d",), band_rows=band_rows, progress=lambda split, sid: done.append(sid))
    wall, cpu = time.perf_counter() - t1, time.process_time() - c1
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    r = result.results[("2d", "CSA")]
    payload = {"gaussians": args.gaussians, "views": args.views, "image": "584x876", "band_rows": band_rows,
               "setup_s": setup_s, "eval_wall_s": wall, "eval_cpu_s": cpu, "wall_s_per_view": wall / args.views,
               "peak_rss_gb": peak, "peak_rss_after_setup_gb": rss_setup, "views_scored": r.num_views,
               "pixels_scored": int(r.scores.num_samples), "cpus": os.cpu_count(), "loadavg": os.getloadavg()}
    print(json.dumps(payload))
    ok = peak <= args.max_peak_gb
    print(f"2D bench, 1 scene x {args.gaussians:,} Gaussians, {args.views} views 584x876, bands of {band_rows} rows: "
          f"{wall:.1f} s wall ({wall / args.views:.2f} s/view), {cpu:.1f} s CPU, peak {peak:.2f} GB "
          f"(after scene set-up {rss_setup:.2f} GB) -> {'within' if ok else 'FAILED: over'} {args.max_peak_gb} GB")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
