"""The recipe works on fitted splats (issue #27), on a tiny case: rooms fitted on the CPU as users bring scenes,
a run trained on the fitted train rooms, and the same val room scored as its fitted splat and as Gaussians sampled
on its mesh. The model must score both within a tolerance, above the majority baseline (the full figure, with
intervals over many rooms, is the benchmark profile's: BENCHMARKS.md, "Model accuracy")."""

from __future__ import annotations

from dataclasses import replace

import pytest

#: Largest gap in val 3D CSA (mIoU) between the room's oracle Gaussians and its fitted splat, same run, as a share of
#: the larger of the two. Measured at this size (4 rooms of 64x48, 30 epochs): fitted 0.048, oracle 0.076, majority
#: 0.027 (the tiny run learns the large classes only; the full figure is the profile's).
CSA_GAP_SHARE = 0.5
#: Both scores must beat the majority baseline by this factor.
ABOVE_MAJORITY = 1.5


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    from seggaussian.pipeline.dataset import build_dataset
    from seggaussian.pipeline.config import BuildConfig, SplitConfig
    from seggaussian.labels.config import OracleConfig
    from seggaussian.fit.config import FitConfig
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("fitted")
    raw = root / "raw"
    synthesize(raw / "scannetpp", 4, 0, "scannetpp", SynthConfig(width=64, num_views=16, max_edge=0.2))
    split = SplitConfig(ratios=(3, 1, 0), seed=0)
    fit = replace(FitConfig.profile().with_iterations(80), max_gaussians=8000)
    common = dict(source="synthetic", root=raw, jobs=1, seed=0, progress=False, split=split)
    fitted = build_dataset(BuildConfig(out=root / "fitted", gaussians="fit", fit="always", fit_config=fit, **common))
    oracle = build_dataset(BuildConfig(out=root / "oracle", gaussians="oracle",
                                       oracle=OracleConfig(num_gaussians=6000), **common))
    assert fitted.counts["failed"] == 0 and oracle.counts["failed"] == 0
    return root / "fitted", root / "oracle"


def val_csa(dataset, run=None, predictor="model") -> float:
    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.bench.config import BenchConfig

    report = run_bench(BenchConfig(dataset=dataset, run=run, predictor=predictor, metrics=("CSA",), dims=("3d",),
                                   progress=False))
    return float(report.payload["metrics"]["3d"]["CSA"]["miou"])


@pytest.mark.slow
def test_a_run_trained_on_fitted_splats_scores_a_room_alike_as_splat_and_as_oracle(datasets, tmp_path):
    from ovgaussian.train.loop import train
    from ovgaussian.run.config import DataConfig, LossConfig, OptimConfig, TrainConfig

    fitted, oracle = datasets
    from seggaussian import shards

    assert shards.list_scenes(fitted, "val") == shards.list_scenes(oracle, "val")
    config = TrainConfig(out=tmp_path / "run", epochs=30, batch_scenes=3, seed=0, model_preset="slim",
                         voxel_size=0.1, use_coordinates=True, progress=False,
                         data=DataConfig(dataset=fitted, pixels_per_view=1024),
                         loss=LossConfig(class_balance=0.5), optim=OptimConfig(lr=0.05))
    train(config)
    on_fit, on_oracle = val_csa(fitted, tmp_path / "run"), val_csa(oracle, tmp_path / "run")
    majority = val_csa(fitted, predictor="majority")
    print(f"val 3D CSA: fitted {on_fit:.3f}, oracle {on_oracle:.3f}, majority {majority:.3f}")
    assert on_fit > ABOVE_MAJORITY * majority and on_oracle > ABOVE_MAJORITY * majority, (on_fit, on_oracle, majority)
    assert abs(on_fit - on_oracle) <= CSA_GAP_SHARE * max(on_fit, on_oracle), (on_fit, on_oracle)
