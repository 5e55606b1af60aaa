"""Benchmark of one OVGaussian training step: 3 scenes x 50,000 Gaussians, one 292x438 view each.

Measures, per configuration (each in a fresh subprocess so that peak RSS is its own):
- preparing one view (label map; since issue 17 the blend weights are computed in each step at the
  sampled pixels, so they are part of the step),
- a full optimizer step (sampling + augmentation, network forward, M = W S, the three losses,
  backward, SGD step), median of ``--steps`` after one warm-up step,
- the CPU time of the process during a step (all threads; less sensitive to other load than wall time),
- the process's peak resident memory (ru_maxrss) and the peak growth during the steps.

The teacher features are random ``[P, D]`` stand-ins (the MaskCLIP pass runs once per view and is
cached, so it is not part of a step); text embeddings are random unit vectors of width 384 (MiniLM).

    .venv/bin/python benchmarks/bench_train.py                     # all configurations, markdown table
    .venv/bin/python benchmarks/bench_train.py --one slim 16384     # a single configuration, JSON
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

NUM_SCENES = 3
NUM_GAUSSIANS = 50_000
WIDTH, HEIGHT = 438, 292
CONFIGS = (("slim", 16384), ("slim", None), ("default", 16384), ("default", None))


def make_scene(seed: int):
    """A 6 x 5 x 3 m room: Gaussians on the floor, walls and ceiling plus furniture boxes, labelled."""
    import numpy as np

    from seggaussian.core.cameras import Camera, intrinsics, look_at
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.shards import SceneRecord, ViewRecord

    rng = np.random.default_rng(seed)
    n = NUM_GAUSSIANS
    surface = rng.integers(0, 6, n)  # 0 floor, 1 ceiling, 2-5 walls
    p = rng.uniform([0, 0, 0], [6, 5, 3], size=(n, 3))
    p[surface == 0, 2] = 0.0
    p[surface == 1, 2] = 3.0
    p[surface == 2, 0] = 0.0
    p[surface == 3, 0] = 6.0
    p[surface == 4, 1] = 0.0
    p[surface == 5, 1] = 5.0
    furniture = rng.random(n) < 0.3
    p[furniture] = rng.uniform([1, 1, 0], [5, 4, 1.2], size=(int(furniture.sum()), 3))
    labels = np.where(furniture, rng.choice([3, 9, 23, 6], n), np.choose(np.minimum(surface, 2), [2, 1, 0]))
    g = Gaussians.from_arrays(p, rng.normal(size=(n, 4)), np.log(rng.uniform(0.01, 0.05, (n, 3))),
                              rng.normal(2.0, 1.0, n), rng.normal(0, 0.5, (n, 1, 3)),
                              extras={"semantic": labels.astype(np.int32)})
    cam = Camera(intrinsics(300.0, 300.0, WIDTH / 2, HEIGHT / 2), look_at([0.5, 0.5, 1.6], [4.0, 3.5, 1.0]),
                 WIDTH, HEIGHT)
    semantic = rng.choice([0, 1, 2, 3], size=(HEIGHT, WIDTH)).astype(np.int32)
    view = ViewRecord("view0", "train", cam, np.zeros((HEIGHT, WIDTH, 3), np.uint8), semantic, semantic)
    return SceneRecord(f"bench{seed}", "synthetic", g, [view])


def run_one(preset: str, pixels: int | None, steps: int) -> dict:
    import numpy as np
    import torch

    from ovgaussian.run.checkpoint import build_network
    from ovgaussian.data.training_data import TrainingData
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.train.loop import make_model_config
    from ovgaussian.run.config import DataConfig, TrainConfig
    from ovgaussian.train.step_losses import batch_losses
    from ovgaussian.text.vocabulary import training_vocabulary

    config = TrainConfig(model_preset=preset, data=DataConfig(pixels_per_view=pixels))
    vocabulary = training_vocabulary(20)
    records = [make_scene(s) for s in range(NUM_SCENES)]
    data = TrainingData(InMemorySource(records), config.data, vocabulary)
    t0 = time.perf_counter()
    for r in records:
        data.prepared_view(r.scene_id, "view0")
    blend_seconds = (time.perf_counter() - t0) / NUM_SCENES
    text = torch.nn.functional.normalize(torch.randn(len(vocabulary.class_ids), 384), dim=1)
    net = build_network(make_model_config(config, 384)).train()
    optimizer = torch.optim.SGD(net.parameters(), lr=0.02, momentum=0.9)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times, cpu_times = [], []
    for step in range(steps + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        samples = [data.sample(r.scene_id, np.random.default_rng([step, i])) for i, r in enumerate(records)]
        samples = [s._replace(teacher=torch.randn(len(s.pixels), 384)) for s in samples]
        optimizer.zero_grad(set_to_none=True)
        terms = batch_losses(net, samples, text, config, True, "cpu")
        loss = sum(t.total for t in terms) / len(terms)
        loss.backward()
        optimizer.step()
        if step > 0:
            times.append(time.perf_counter() - t0)
            cpu_times.append(time.process_time() - c0)
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"preset": preset, "pixels_per_view": pixels, "gaussians_per_scene": NUM_GAUSSIANS,
            "scenes": NUM_SCENES, "image": f"{HEIGHT}x{WIDTH}", "blend_weights_s_per_view": blend_seconds,
            "step_s_median": statistics.median(times), "step_s_all": times,
            "step_cpu_s_median": statistics.median(cpu_times),
            "peak_rss_mb": rss_after / 1024, "peak_growth_during_steps_mb": (rss_after - rss_before) / 1024,
            "torch_threads": torch.get_num_threads(), "parameters": sum(p.numel() for p in net.parameters()),
            "loss": float(loss.detach())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--one", nargs=2, metavar=("PRESET", "PIXELS"), help="run one configuration (PIXELS or 'all')")
    parser.add_argument("--steps", type=int, default=3)
    args = parser.parse_args()
    if args.one:
        preset, pixels = args.one
        print(json.dumps(run_one(preset, None if pixels == "all" else int(pixels), args.steps)))
        return
    rows = []
    for preset, pixels in CONFIGS:
        cmd = [sys.executable, __file__, "--one", preset, "all" if pixels is None else str(pixels),
               "--steps", str(args.steps)]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            print(done.stderr[-2000:], file=sys.stderr)
            continue
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print("| preset | pixels/view | params | prepare view | step wall (median) | step CPU (median) | peak RSS |"
          " growth in steps |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        px = "all (127,896)" if r["pixels_per_view"] is None else f"{r['pixels_per_view']:,}"
        print(f"| {r['preset']} | {px} | {r['parameters']:,} | {r['blend_weights_s_per_view']:.2f} s | "
              f"{r['step_s_median']:.2f} s | {r['step_cpu_s_median']:.2f} s | {r['peak_rss_mb']:.0f} MB | {r['peak_growth_during_steps_mb']:.0f} MB |")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
