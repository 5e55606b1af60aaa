"""Benchmark: the occlusion test of the label transfer (``seggaussian.labels.occlusion``), its cost per room and what
it drops.

Synthetic ScanNet++-layout rooms (``seggaussian.sources.synthetic``, the profile's 160-px width and 32 views): for each,
the label points the transfer stage uses (mesh vertices plus samples 0.03 m apart on the faces), then
``occluded_points`` against the room's train views, timed (median of ``--reps`` calls). Prints a markdown table with
the points, the share occluded and the time, then the mean.

    .venv/bin/python benchmarks/bench_occlusion.py --rooms 4 --reps 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rooms", type=int, default=4)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from seggaussian.labels.config import TransferConfig
    from seggaussian.labels.occlusion import occluded_points
    from seggaussian.labels.transfer import densify_labelled_mesh
    from seggaussian.sources.scannetpp import read_scene
    from seggaussian.sources.synthetic import generate as synthetic

    spacing = TransferConfig().mesh_sample_spacing
    print("| room | label points | train views | occluded | time (s) |\n|---|---:|---:|---:|---:|")
    times, shares = [], []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "scannetpp"
        ids = synthetic.synthesize(root, args.rooms, args.seed, "scannetpp",
                                   synthetic.SynthConfig(width=160, num_views=32))
        for scene_id in ids:
            scene = read_scene(root, scene_id)
            samples, _ = densify_labelled_mesh(scene.points, scene.faces, spacing, scene.semantic)
            points = np.concatenate([scene.points, samples])
            cameras = [v.camera for v in scene.views if v.role == "train"]
            runs = []
            for _ in range(args.reps):
                start = time.perf_counter()
                occluded = occluded_points(scene.points, scene.faces, points, cameras)
                runs.append(time.perf_counter() - start)
            times.append(statistics.median(runs))
            shares.append(float(occluded.mean()))
            print(f"| {scene_id} | {len(points):,} | {len(cameras)} | {shares[-1]:.1%} | {times[-1]:.2f} |")
    print(f"\nmean over {len(times)} rooms: {statistics.mean(times):.2f} s, {statistics.mean(shares):.1%} occluded")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
