"""Benchmark: the occlusion test of the label transfer (``seggaussian.labels.occlusion``), its cost per room and what
it drops.

Synthetic ScanNet++-layout rooms (``seggaussian.sources.synthetic``, the profile's 160-px width and 32 views): for each,
the label points the transfer stage uses (mesh vertices plus samples 0.03 m apart on the faces), then
``occluded_points`` against the room's train views, timed (median of ``--reps`` calls); then ``on_hidden_surface``
(which Gaussians lie on a surface no train view sees) for two kinds of splat of the room: a Gaussian at every mesh
vertex (a scan turned into splats) and 40,000 oracle Gaussians on the seen surfaces (as a fit places them), timed
the same way, with the share of Gaussians it finds. Prints a markdown table, then the means.

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

    from seggaussian.labels.config import OracleConfig, TransferConfig
    from seggaussian.labels.occlusion import occluded_points, on_hidden_surface
    from seggaussian.labels.oracle import sample_oracle_gaussians
    from seggaussian.labels.transfer import densify_labelled_mesh
    from seggaussian.sources.scannetpp import read_scene
    from seggaussian.sources.synthetic import generate as synthetic

    spacing = TransferConfig().mesh_sample_spacing
    print("| room | label points | train views | occluded | time (s) | vertex Gaussians on hidden | time (s) "
          "| oracle Gaussians on hidden | time (s) |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    columns = {"occlusion": [], "share": [], "vertex": [], "vertex_share": [], "oracle": [], "oracle_share": []}

    def timed(call):
        runs, out = [], None
        for _ in range(args.reps):
            start = time.perf_counter()
            out = call()
            runs.append(time.perf_counter() - start)
        return out, statistics.median(runs)

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "scannetpp"
        ids = synthetic.synthesize(root, args.rooms, args.seed, "scannetpp",
                                   synthetic.SynthConfig(width=160, num_views=32))
        for scene_id in ids:
            scene = read_scene(root, scene_id)
            samples, _ = densify_labelled_mesh(scene.points, scene.faces, spacing, scene.semantic)
            points = np.concatenate([scene.points, samples])
            cameras = [v.camera for v in scene.views if v.role == "train"]
            occluded, seconds = timed(lambda: occluded_points(scene.points, scene.faces, points, cameras))
            columns["occlusion"].append(seconds)
            columns["share"].append(float(occluded.mean()))
            oracle, _ = sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces, OracleConfig(),
                                                np.random.default_rng(args.seed), tuple(cameras))
            row = f"| {scene_id} | {len(points):,} | {len(cameras)} | {columns['share'][-1]:.1%} | {seconds:.2f} "
            for name, means in (("vertex", scene.points), ("oracle", oracle.means)):
                hits, seconds = timed(lambda: on_hidden_surface(means, scene.points, scene.faces, cameras))
                columns[name].append(seconds)
                columns[f"{name}_share"].append(len(hits.rows) / len(means))
                row += f"| {len(hits.rows):,} of {len(means):,} | {seconds:.2f} "
            print(row + "|")
    mean = {k: statistics.mean(v) for k, v in columns.items()}
    print(f"\nmean over {len(ids)} rooms: occlusion test {mean['occlusion']:.2f} s ({mean['share']:.1%} occluded); "
          f"on_hidden_surface {mean['vertex']:.2f} s for vertex Gaussians ({mean['vertex_share']:.1%} on hidden "
          f"surfaces), {mean['oracle']:.2f} s for oracle Gaussians ({mean['oracle_share']:.1%})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
