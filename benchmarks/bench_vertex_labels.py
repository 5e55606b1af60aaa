"""Benchmark: a scan turned into splats keeps its labels through the transfer stage, however few views there are.

A synthetic ScanNet++-layout room (``seggaussian synth``), a small Gaussian at every mesh vertex, and only the first
``--views`` train views: the transfer stage (``seggaussian.pipeline.stages.transfer.run_transfer``, occlusion test on)
should give each Gaussian its vertex's label. Reported per room: the labelled vertices, how many labels the occlusion
test alone would change (to ignore, to another class, ignore to a class: occluded points dropped from the candidates,
nothing else), how many the stage changes, the Gaussians it finds on hidden surfaces and the stage's time.

    .venv/bin/python benchmarks/bench_vertex_labels.py --rooms 2 --views 2
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def changes(got: np.ndarray, truth: np.ndarray, ignore: int) -> tuple[int, int, int]:
    """(labelled -> ignore, labelled -> another class, ignore -> a class)."""
    labelled = truth != ignore
    return (int((labelled & (got == ignore)).sum()), int((labelled & (got != ignore) & (got != truth)).sum()),
            int((~labelled & (got != ignore)).sum()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rooms", type=int, default=2)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--width", type=int, default=96)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.labels.transfer import densify_labelled_mesh, transfer_labels
    from seggaussian.pipeline.config import BuildConfig
    from seggaussian.pipeline.stages import transfer as stage
    from seggaussian.sources.scannetpp import read_scene
    from seggaussian.sources.synthetic import generate as synthetic

    print("| room | labelled vertices | occlusion test alone: to ignore / to another class / ignore to a class "
          "| the stage: same three | on hidden surfaces | stage time (s) |\n|---|---:|---|---|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "scannetpp"
        ids = synthetic.synthesize(root, args.rooms, args.seed, "scannetpp",
                                   synthetic.SynthConfig(width=args.width, num_views=8))
        for scene_id in ids:
            scene = read_scene(root, scene_id)
            scene = replace(scene, views=tuple(v for v in scene.views if v.role == "train")[: args.views])
            n = len(scene.points)
            g = Gaussians.from_arrays(scene.points, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), -5.0),
                                      np.zeros(n), np.zeros((n, 1, 3)))
            config = BuildConfig(source="synthetic", root=root, out=Path(tmp) / "out")
            config = replace(config, transfer=replace(config.transfer, min_on_mesh_share=0.0))
            truth = scene.semantic.astype(np.int32)
            start = time.perf_counter()
            labelled, facts = stage.run_transfer(scene, g, truth, config)
            seconds = time.perf_counter() - start
            samples, (s_sem, s_inst) = densify_labelled_mesh(scene.points, scene.faces,
                                                             config.transfer.mesh_sample_spacing, scene.semantic,
                                                             scene.instance)
            points = np.concatenate([scene.points, samples])
            hidden = stage.occluded_label_points(scene, points, config.transfer.occlusion_tolerance)
            alone = transfer_labels(scene.points, points, np.concatenate([scene.semantic, s_sem]),
                                    np.concatenate([scene.instance, s_inst]), None, config.transfer, hidden=hidden)
            before = changes(alone.semantic, truth, IGNORE_LABEL)
            after = changes(labelled.extras["semantic"], truth, IGNORE_LABEL)
            print(f"| {scene_id} | {int((truth != IGNORE_LABEL).sum()):,} | {' / '.join(f'{c:,}' for c in before)} | "
                  f"{' / '.join(f'{c:,}' for c in after)} | {facts['transfer']['on_hidden_surface']:,} | {seconds:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
