"""The run folder after a demo-like training stays within the cache budget (issue 17)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ovgaussian.data.cache_budget import CACHE_BUDGET_FRACTION, folder_bytes, run_cache_usage

synthetic = pytest.importorskip("seggaussian.sources.synthetic.generate")


def test_folder_bytes_counts_files_and_skips_internal_folders(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.bin").write_bytes(b"0" * 100)
    (tmp_path / ".build").mkdir()
    (tmp_path / ".build" / "y.bin").write_bytes(b"0" * 1000)
    (tmp_path / "z.json").write_bytes(b"0" * 10)
    assert folder_bytes(tmp_path) == 1110
    assert folder_bytes(tmp_path, (".build",)) == 110
    assert folder_bytes(tmp_path / "missing") == 0
    run = tmp_path / "run"
    (run / "caches" / "teacher_abc").mkdir(parents=True)
    (run / "caches" / "teacher_abc" / "v.safetensors").write_bytes(b"0" * 7)
    (run / "caches" / "text_minilm_k.safetensors").write_bytes(b"0" * 3)
    usage = run_cache_usage(run, tmp_path / "a")
    assert usage.by_kind == {"teacher": 7, "text": 3} and usage.cache_bytes == 10 and usage.dataset_bytes == 100
    assert usage.within_budget and abs(usage.fraction - 0.1) < 1e-12
    (run / "caches" / "blend_k16").mkdir()
    (run / "caches" / "blend_k16" / "w.safetensors").write_bytes(b"0")
    assert not run_cache_usage(run, tmp_path / "a").within_budget


def test_run_folder_after_a_demo_like_training_stays_within_the_cache_budget(tmp_path):
    """synth -> build (oracle Gaussians, labels, label maps, shards, split) -> train with the MiniLM text
    encoder and a MaskCLIP teacher, as scripts/demo.sh does at a smaller size: the run's caches (text
    embeddings, patch-resolution teacher features) are at most 10 % of the dataset, and no per-view
    blend weights are written anywhere."""
    from tiny_clip import random_clip

    from ovgaussian.text.teacher import DenseTeacher
    from ovgaussian.train.loop import train
    from ovgaussian.run.config import DataConfig, TeacherConfig, TrainConfig
    from seggaussian.pipeline import dataset as build_mod
    from seggaussian.pipeline.config import BuildConfig
    from seggaussian.labels.config import OracleConfig
    from test_train import tiny_model_config

    raw = tmp_path / "raw"
    cfg = synthetic.SynthConfig(width=64, num_views=5)
    synthetic.synthesize(raw / "scannetpp", 2, 0, "scannetpp", cfg)
    dataset = tmp_path / "dataset"
    build_mod.build_dataset(BuildConfig(source="synthetic", root=raw, out=dataset, gaussians="oracle",
                                        progress=False, oracle=OracleConfig(num_gaussians=3000)))
    # ViT-B/16's patch size and feature width: the cache bytes of the real one
    clip = random_clip(image_size=32, patch_size=16, projection_dim=512)
    teacher = DenseTeacher(clip, TeacherConfig(short_side=64))
    run = tmp_path / "run"
    result = train(TrainConfig(data=DataConfig(dataset=dataset, pixels_per_view=512), out=run, epochs=2,
                               batch_scenes=1, seed=0, progress=False), teacher=teacher,
                   model_config=tiny_model_config(384))
    usage = run_cache_usage(run, dataset)
    assert set(usage.by_kind) <= {"text", "teacher"} and usage.by_kind["text"] > 0, usage.by_kind
    assert usage.dataset_bytes > 100_000
    # 512-wide patch features of a 64x48 view are larger than the view itself: the budget stops caching them
    assert any("without caching" in note for note in result.notes), result.notes
    assert usage.within_budget, (f"run caches {usage.cache_bytes:,} B = {100 * usage.fraction:.1f} % of the "
                                 f"dataset's {usage.dataset_bytes:,} B (budget {100 * CACHE_BUDGET_FRACTION:.0f} %)")
    written = [p for p in Path(run).rglob("*") if p.is_file()] + [p for p in dataset.rglob("*") if p.is_file()]
    assert not [p for p in written if "blend" in p.name or "blend" in p.parent.name]


def test_teacher_cache_stops_at_the_budget_and_features_stay_exact(tmp_path):
    """Past the budget, teacher features are computed per use (counted), equal to the cached ones."""
    import numpy as np
    from tiny_clip import random_clip

    from ovgaussian.data.training_data import TrainingData
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.text.teacher import DenseTeacher
    from ovgaussian.run.config import DataConfig, TeacherConfig
    from ovgaussian.text.vocabulary import training_vocabulary
    from test_train import make_scene

    clip = random_clip()
    teacher = DenseTeacher(clip, TeacherConfig(short_side=16))
    scenes = [make_scene(0, per_box=10, views=4)]  # 3 train views
    grid = teacher.compute_patch_features(scenes[0].views[0].rgb).patch_features
    assert grid.shape == (2, 3, 20)
    one_file = grid.numel() * 4 + 512  # float32 features of the patch grid plus the header allowance
    data = TrainingData(InMemorySource(scenes), DataConfig(view_cache_size=1), training_vocabulary(20),
                          cache_dir=tmp_path, teacher=teacher, cache_budget_bytes=one_file + 10)
    views = scenes[0].views[:3]
    got = [data.prepared_view("scene00", v.name).teacher for v in views]
    assert len(list(tmp_path.rglob("*.safetensors"))) == 1 and data.teacher_uncached == 2
    assert sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file()) <= one_file + 10
    for view, features in zip(views, got):
        torch.testing.assert_close(features, teacher.compute_patch_features(view.rgb).patch_features, rtol=0, atol=0)
    unlimited = TrainingData(InMemorySource(scenes), DataConfig(), training_vocabulary(20),
                               cache_dir=tmp_path / "all", teacher=teacher)
    for view in views:
        unlimited.prepared_view("scene00", view.name)
    assert len(list((tmp_path / "all").rglob("*.safetensors"))) == 3 and unlimited.teacher_uncached == 0
    assert np.isfinite(got[0].numpy()).all()
