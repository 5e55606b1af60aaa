"""Budget benchmark: run-folder caches <= 10 % of the dataset's size (issue 17).

Two measurements, each printed with its figure; exit status 1 when a budget is missed:

1. ``--data DATASET --run RUN`` (e.g. the demo's ``out/demo/dataset`` and ``out/demo/run``): bytes of
   ``RUN/caches`` against the dataset's bytes (``ovgaussian.data.cache_budget.run_cache_usage``).
2. A paper-scale scene (``--gaussians`` 1,000,000 Gaussians with SH degree 3, ``--views`` 584x876 train
   views) written as the dataset's Parquet tables (gaussians + views, default ShardConfig) to measure
   its bytes, then every view prepared by ``TrainingData`` as training does, with a MaskCLIP teacher of
   ViT-B/16's patch size and feature width (random weights: the cache bytes are those of the real
   model) and the run's cache budget. Reported: the run caches, and the per-view cache bytes before
   (the whole view's top-16 blend weights, int32 ids + float32 weights, as the trainer used to store
   them; computed from the layout) and after (no blend weights; teacher patch features while within
   the budget).

    .venv/bin/python benchmarks/bench_cache_budget.py --data out/demo/dataset --run out/demo/run
    .venv/bin/python benchmarks/bench_cache_budget.py --gaussians 1000000 --views 50
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

TOP_K = 16


def old_blend_cache_bytes(height: int, width: int, top_k: int = TOP_K) -> int:
    """Bytes of the former per-view cache: ids int32 + weights float32 per pixel and slot (+ header)."""
    return height * width * top_k * (4 + 4) + 200


def measure_run(data: Path, run: Path) -> dict:
    from ovgaussian.data.cache_budget import run_cache_usage

    usage = run_cache_usage(run, data)
    return {"what": f"run {run} on {data}", "cache_bytes": usage.cache_bytes, "dataset_bytes": usage.dataset_bytes,
            "by_kind": usage.by_kind, "fraction": usage.fraction, "within_budget": usage.within_budget}


def measure_paper_scene(num_gaussians: int, num_views: int, workdir: Path) -> dict:
    import numpy as np
    import torch
    from transformers import CLIPConfig, CLIPModel

    from bench_paper_step import HEIGHT, WIDTH, make_room
    from ovgaussian.data.cache_budget import CACHE_BUDGET_FRACTION, folder_bytes
    from ovgaussian.data.training_data import TrainingData
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.text.teacher import DenseTeacher
    from ovgaussian.run.config import DataConfig, TeacherConfig
    from ovgaussian.text.vocabulary import training_vocabulary
    from seggaussian import shards
    from seggaussian.shards.config import ShardConfig
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.render import render_gaussians

    t0 = time.perf_counter()
    scene = make_room(0, num_gaussians, views=num_views)
    g = scene.gaussians
    rng = np.random.default_rng(1)
    sh = np.concatenate([g.sh, rng.normal(0, 0.05, (len(g), 15, 3)).astype(np.float32)], axis=1)  # SH degree 3
    extras = dict(g.extras, instance=(g.extras["semantic"] * 7 + rng.integers(0, 5, len(g))).astype(np.int32),
                  transfer_distance=rng.uniform(0, 0.02, len(g)).astype(np.float32))
    g = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, sh, extras)
    rows = []
    views = []
    for view in scene.views:  # real RGB renders and a blocky label map: realistic encoded sizes
        rgb = render_gaussians(g, view.camera).image.clamp(0, 1).mul(255).round().to(torch.uint8).numpy()
        sem = (np.arange(HEIGHT)[:, None] // 60 * 7 + np.arange(WIDTH)[None, :] // 90).astype(np.int32) % 20
        rows.append(shards.ViewRow(view.name, "train", view.camera, shards.encode_rgb(rgb),
                                   shards.encode_label_map(sem), shards.encode_label_map(sem // 2), 1.0))
        views.append(view._replace(rgb=rgb, semantic=sem))
    config = ShardConfig()
    dataset = workdir / "dataset"
    for name, table in (("gaussians", shards.gaussians_table(scene.scene_id, g)),
                        ("views", shards.views_table(scene.scene_id, rows))):
        shards.write_parquet_atomic(dataset / f"{name}.parquet", name, [table], config)
    dataset_bytes = folder_bytes(dataset)
    render_s = time.perf_counter() - t0

    torch.manual_seed(0)
    clip = CLIPModel(CLIPConfig(
        text_config=dict(hidden_size=16, intermediate_size=16, num_hidden_layers=1, num_attention_heads=2,
                         vocab_size=40, max_position_embeddings=8, bos_token_id=0, eos_token_id=1, pad_token_id=1),
        vision_config=dict(hidden_size=32, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2,
                           image_size=224, patch_size=16),
        projection_dim=512)).eval()
    teacher = DenseTeacher(clip, TeacherConfig())  # short side 224, patch 16, D = 512: ViT-B/16's cache bytes
    run = workdir / "run"
    budget = int(CACHE_BUDGET_FRACTION * dataset_bytes)
    data = TrainingData(InMemorySource([scene._replace(gaussians=g, views=views)]),
                        DataConfig(pixels_per_view=16384, view_cache_size=1), training_vocabulary(20),
                        cache_dir=run / "caches", teacher=teacher, cache_budget_bytes=budget)
    t1 = time.perf_counter()
    for i, view in enumerate(views):
        data.prepared_view(scene.scene_id, view.name)
    sample = data.sample(scene.scene_id, np.random.default_rng(0))
    prepare_s = time.perf_counter() - t1
    cache_bytes = folder_bytes(run / "caches")
    teacher_files = list((run / "caches").rglob("*.safetensors"))
    per_view_teacher = teacher_files[0].stat().st_size if teacher_files else 0
    return {"what": f"paper-scale scene: {num_gaussians:,} Gaussians (SH 3), {num_views} views {HEIGHT}x{WIDTH}",
            "dataset_bytes": dataset_bytes, "cache_bytes": cache_bytes, "fraction": cache_bytes / dataset_bytes,
            "within_budget": cache_bytes <= budget, "budget_bytes": budget,
            "per_view_before_bytes": old_blend_cache_bytes(HEIGHT, WIDTH) + per_view_teacher,
            "per_view_blend_before_bytes": old_blend_cache_bytes(HEIGHT, WIDTH),
            "per_view_after_bytes_cached_teacher": per_view_teacher, "teacher_files": len(teacher_files),
            "teacher_uncached": data.teacher_uncached, "sampled_pixels": int(sample.pixels.shape[0]),
            "write_dataset_s": render_s, "prepare_views_s": prepare_s}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="dataset of a finished run (measurement 1)")
    parser.add_argument("--run", type=Path, help="run folder trained on --data (measurement 1)")
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--views", type=int, default=50)
    parser.add_argument("--skip-paper", action="store_true", help="only measurement 1")
    args = parser.parse_args()
    results = []
    if args.data is not None and args.run is not None:
        results.append(measure_run(args.data, args.run))
    if not args.skip_paper:
        with tempfile.TemporaryDirectory(prefix="cache-budget-") as tmp:
            results.append(measure_paper_scene(args.gaussians, args.views, Path(tmp)))
    print(json.dumps(results))
    failed = False
    for r in results:
        status = "within budget" if r["within_budget"] else "FAILED: over the 10 % budget"
        failed |= not r["within_budget"]
        print(f"{r['what']}: caches {r['cache_bytes']:,} B / dataset {r['dataset_bytes']:,} B = "
              f"{100 * r['fraction']:.2f} % -> {status}")
        if "per_view_blend_before_bytes" in r:
            print(f"  per view: before {r['per_view_before_bytes']:,} B (blend weights "
                  f"{r['per_view_blend_before_bytes']:,} B + teacher), after: no blend weights, teacher "
                  f"{r['per_view_after_bytes_cached_teacher']:,} B for {r['teacher_files']} views, "
                  f"{r['teacher_uncached']} computed uncached (budget)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
