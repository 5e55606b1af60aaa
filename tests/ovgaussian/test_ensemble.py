"""An ensemble of runs as one predictor: scores averaged over members, each member on its own vector columns."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ovgaussian.predict.ensemble import EnsemblePredictor


class _LinearMember:
    """A member with ``width``-d vectors: encode = a fixed projection of the scene's points, classify = tanh of a
    linear map (a nonlinear score, as phi plus cosine is)."""

    def __init__(self, seed: int, width: int, classes: int = 5) -> None:
        rng = np.random.default_rng(seed)
        self.project = rng.normal(size=(3, width)).astype(np.float32)
        self.weights = rng.normal(size=(width, classes)).astype(np.float32)

    def encode(self, scene) -> np.ndarray:
        return (scene @ self.project).astype(np.float32)

    def classify(self, vectors, class_ids):
        return np.tanh(np.asarray(vectors) @ self.weights[:, : len(class_ids)])


def test_ensemble_scores_are_the_members_mean_also_after_a_linear_blend():
    """encode is the members' vectors side by side; classify of a linear blend of them (a rendered pixel) is the
    mean of each member's classify of the same blend of its own vectors; one member is that member."""
    members = [_LinearMember(0, 4), _LinearMember(1, 6), _LinearMember(2, 4)]
    ensemble = EnsemblePredictor(members, [4, 6, 4])
    scene = np.random.default_rng(3).normal(size=(50, 3)).astype(np.float32)
    class_ids = np.arange(5)
    vectors = ensemble.encode(scene)
    assert vectors.shape == (50, 14)
    np.testing.assert_array_equal(vectors[:, 4:10], members[1].encode(scene))
    blend = np.random.default_rng(4).random((7, 50)).astype(np.float32)  # 7 pixels' blend weights
    want = np.mean([m.classify(blend @ m.encode(scene), class_ids) for m in members], axis=0)
    np.testing.assert_allclose(ensemble.classify(blend @ vectors, class_ids), want, rtol=1e-5, atol=1e-6)
    single = EnsemblePredictor(members[:1], [4])
    np.testing.assert_allclose(single.classify(single.encode(scene), class_ids),
                               members[0].classify(members[0].encode(scene), class_ids), rtol=1e-6)


def test_ensemble_refuses_mismatched_widths():
    with pytest.raises(ValueError, match="one semantic width per member"):
        EnsemblePredictor([_LinearMember(0, 4)], [4, 4])
    ensemble = EnsemblePredictor([_LinearMember(0, 4)], [5])
    with pytest.raises(ValueError, match="expected width 5"):
        ensemble.encode(np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match="expected width 5"):
        ensemble.classify(np.zeros((3, 4), np.float32), np.arange(2))


def test_bench_scores_an_ensemble_of_runs(tmp_path):
    """End to end on shards: ``ovgaussian bench --ensemble-run`` records every member's checkpoint; an ensemble of a
    run with itself scores what the run alone scores; one with a second seed is scored; with --stacking-run or a
    baseline predictor it is a one-line error."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from test_train import _write_shards, make_scene

    data = tmp_path / "data"
    _write_shards(data, [make_scene(s, per_box=20, views=2) for s in range(2)])
    for seed in (0, 1):
        trained = CliRunner().invoke(main, ["train", "--data", str(data), "--epochs", "1", "--model-preset", "slim",
                                            "--pixels-per-view", "64", "--batch-scenes", "2", "--no-progress",
                                            "--seed", str(seed), "--out", str(tmp_path / f"run{seed}")])
        assert trained.exit_code == 0, trained.output
    common = ["bench", "--data", str(data), "--run", str(tmp_path / "run0"), "--dim", "2d", "--metric", "NVA",
              "--max-views", "1", "--no-progress"]

    def row(*extra):
        out = tmp_path / f"bench{len(list(tmp_path.glob('bench*.json')))}.json"
        result = CliRunner().invoke(main, common + [*extra, "--out", str(out)])
        assert result.exit_code == 0, result.output
        return json.loads(out.read_text())

    alone = row()
    doubled = row("--ensemble-run", str(tmp_path / "run0"))
    mixed = row("--ensemble-run", str(tmp_path / "run1"))
    members = mixed["predictor"]["ensemble"]
    assert [m["run"] for m in members] == [str(tmp_path / "run1")] and members[0]["checkpoint_sha256"]
    assert doubled["row"]["2d_NVA"] == pytest.approx(alone["row"]["2d_NVA"], abs=1e-6)
    assert mixed["row"]["2d_NVA"] is not None
    bad = CliRunner().invoke(main, common + ["--ensemble-run", str(tmp_path / "run1"), "--stacking-run",
                                             str(tmp_path / "run1")])
    assert bad.exit_code != 0 and "not supported" in bad.output and "Traceback" not in bad.output
    baseline = CliRunner().invoke(main, ["bench", "--data", str(data), "--predictor", "majority", "--ensemble-run",
                                         str(tmp_path / "run1"), "--no-progress"])
    assert baseline.exit_code != 0 and "does not apply" in baseline.output and "Traceback" not in baseline.output
