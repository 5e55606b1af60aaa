"""Faint Gaussians blended with their opaque neighbours: the k-d tree path against the plain loop, the opacity
rules, degenerate inputs, and the option through ``ovgaussian predict`` and ``ovgaussian bench``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ovgaussian.predict.faint_blend import MIN_WEIGHT, faint_blend, faint_blend_reference


def _cloud(n: int, seed: int, width: int = 5):
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1, 1, size=(n, 3))
    opacity = rng.uniform(0, 1, size=n) ** 2  # many faint ones, as a fit leaves
    vectors = rng.normal(size=(n, width)).astype(np.float32)
    return means, opacity, vectors


@pytest.mark.parametrize("n,k", [(200, 8), (57, 16), (30, 2), (5, 8)])
def test_fast_path_equals_the_reference(n, k):
    means, opacity, vectors = _cloud(n, seed=n + k)
    np.testing.assert_allclose(faint_blend(means, opacity, vectors, k),
                               faint_blend_reference(means, opacity, vectors, k), rtol=1e-5, atol=1e-6)


def test_opaque_gaussians_keep_their_vector_and_faint_ones_take_their_neighbours():
    means, opacity, vectors = _cloud(100, seed=3)
    opacity[:50] = 1.0
    opacity[50:] = 0.0
    out = faint_blend(means, opacity, vectors, 8)
    np.testing.assert_allclose(out[:50], vectors[:50], atol=1e-6)  # a = 1: unchanged
    # a fully transparent Gaussian: the weighted mean of its 8 nearest, its own weight at the floor
    from scipy.spatial import cKDTree

    _, index = cKDTree(means).query(means[50:], k=8)
    weight = np.where(opacity[index] > 0, opacity[index], MIN_WEIGHT)
    want = (weight[..., None] * vectors[index]).sum(1) / weight.sum(1, keepdims=True)
    np.testing.assert_allclose(out[50:], want, rtol=1e-5, atol=1e-6)
    assert not np.allclose(out[50:], vectors[50:])


def test_uniform_vectors_are_a_fixed_point_and_the_blend_is_linear():
    means, opacity, vectors = _cloud(80, seed=4)
    constant = np.tile(np.arange(5, dtype=np.float32), (80, 1))
    np.testing.assert_allclose(faint_blend(means, opacity, constant, 8), constant, rtol=1e-6)
    other = np.random.default_rng(5).normal(size=vectors.shape).astype(np.float32)
    combined = faint_blend(means, opacity, 2 * vectors - other, 8)
    np.testing.assert_allclose(combined, 2 * faint_blend(means, opacity, vectors, 8)
                               - faint_blend(means, opacity, other, 8), atol=1e-5)


def test_degenerate_inputs():
    means, opacity, vectors = _cloud(10, seed=6)
    for k in (0, 1):  # off: a copy, not the input
        out = faint_blend(means, opacity, vectors, k)
        np.testing.assert_array_equal(out, vectors)
        assert out is not vectors
    empty = faint_blend(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 4), np.float32), 8)
    assert empty.shape == (0, 4)
    one = faint_blend(means[:1], np.zeros(1), vectors[:1], 8)  # k clipped to N = 1
    np.testing.assert_array_equal(one, vectors[:1])
    # every Gaussian transparent and at one point: finite, the even mean of the neighbourhood
    same = faint_blend(np.zeros((6, 3)), np.zeros(6), vectors[:6], 6)
    assert np.isfinite(same).all()
    np.testing.assert_allclose(same, np.tile(vectors[:6].mean(0), (6, 1)), rtol=1e-5, atol=1e-6)
    # opacities outside [0, 1] are clipped, as the reference does
    wild = opacity * 3 - 1
    np.testing.assert_allclose(faint_blend(means, wild, vectors, 4), faint_blend_reference(means, wild, vectors, 4),
                               rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="neighbours"):
        faint_blend(means, opacity, vectors, -1)
    with pytest.raises(ValueError, match=r"means \[N, 3\]"):
        faint_blend(means[:, :2], opacity, vectors, 4)
    bad = means.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        faint_blend(bad, opacity, vectors, 4)


def test_the_blend_does_not_depend_on_the_gaussians_order():
    means, opacity, vectors = _cloud(120, seed=7)
    order = np.random.default_rng(8).permutation(120)
    out = faint_blend(means, opacity, vectors, 8)
    np.testing.assert_allclose(faint_blend(means[order], opacity[order], vectors[order], 8), out[order], atol=1e-6)


def test_predict_and_bench_apply_the_blend(tmp_path):
    """The option reaches the model's vectors in ``ovgaussian predict`` (labels = argmax over the blended vectors)
    and in ``ovgaussian bench`` (recorded in the report; its 3D confusion is that of the blended vectors)."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from ovgaussian.predict.query import load_model_predictor
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.io.formats import write_gaussians
    from test_train import _write_shards, make_scene

    def faint(g, seed):  # opacities as a fit leaves them, so the blend changes vectors
        alpha = np.random.default_rng(seed).uniform(0.01, 0.9, size=len(g)).astype(np.float32)
        return Gaussians(g.means, g.quats, g.log_scales, np.log(alpha / (1 - alpha)), g.sh, dict(g.extras))

    data = tmp_path / "data"
    scenes = [make_scene(s, per_box=20, views=2) for s in range(3)]
    _write_shards(data, [scene._replace(gaussians=faint(scene.gaussians, i)) for i, scene in enumerate(scenes)],
                  {"scene02": "val"})
    run = tmp_path / "run"
    trained = CliRunner().invoke(main, ["train", "--data", str(data), "--epochs", "1", "--model-preset", "slim",
                                        "--pixels-per-view", "64", "--batch-scenes", "2", "--no-progress",
                                        "--out", str(run)])
    assert trained.exit_code == 0, trained.output

    g = faint(make_scene(5, per_box=20, views=1).gaussians, 5)
    ply = tmp_path / "scene.ply"
    write_gaussians(ply, g, "ply")
    names = ("chair", "table", "floor", "wall", "sofa")
    plain = load_model_predictor(run)
    vectors = faint_blend(g.means, g.opacities().reshape(-1), plain.encode_gaussians(g), 8)
    scores = plain.score_names(vectors, names)
    margin = np.sort(scores, axis=1)
    clear = margin[:, -1] - margin[:, -2] > 1e-5
    def predict(out, *extra):
        return CliRunner().invoke(main, ["predict", str(ply), "--run", str(run), "--vocab", ", ".join(names),
                                         *extra, "--out", str(tmp_path / out), "--json"])

    result = predict("out.ply", "--faint-neighbours", "8")
    assert result.exit_code == 0, result.output
    from plyfile import PlyData

    labels = np.asarray(PlyData.read(str(tmp_path / "out.ply"))["vertex"]["semantic"])
    np.testing.assert_array_equal(labels[clear], scores.argmax(axis=1)[clear])
    assert load_model_predictor(run, faint_neighbours=8).encode_gaussians(g) == pytest.approx(vectors, abs=1e-5)

    def bench(k, *extra):
        out = tmp_path / f"bench{k}{''.join(extra)}.json"
        ran = CliRunner().invoke(main, ["bench", "--data", str(data), "--run", str(run), "--dim", "3d", "--metric",
                                        "CSA", "--faint-neighbours", str(k), *extra, "--no-progress", "--out", str(out)])
        assert ran.exit_code == 0, ran.output
        return json.loads(out.read_text())

    off, on = bench(0), bench(8)
    assert on["predictor"]["faint_neighbours"] == 8 and off["predictor"]["faint_neighbours"] == 0
    # the bench's 3D confusion is that of the blended vectors, scene by scene
    from ovgaussian.bench.evaluate import classify_vectors
    from ovgaussian.metrics import ConfusionMatrix
    from ovgaussian.text.vocabulary import benchmark_vocabulary, to_vocabulary_labels
    from seggaussian import shards

    vocabulary = benchmark_vocabulary(20)
    for k, report in ((0, off), (8, on)):
        want = ConfusionMatrix(len(vocabulary.class_ids))
        for scene in shards.iter_scenes(data, "val", views=False):
            gs = scene.gaussians
            vectors = plain.encode_gaussians(gs)
            if k:
                vectors = faint_blend(gs.means, gs.opacities().reshape(-1), vectors, k)
            gt = to_vocabulary_labels(gs.extras["semantic"], vocabulary, "test")
            want.update(classify_vectors(plain, vectors, vocabulary, 65536), gt)
        assert want.counts.sum() > 0
        np.testing.assert_array_equal(np.asarray(report["confusion"]["val_3d"]), want.counts)
    # what the bench scores: the blended vectors, for the run and for every ensemble member
    from ovgaussian.bench.config import BenchConfig
    from ovgaussian.bench.evaluate import make_predictor

    scene = next(iter(shards.iter_scenes(data, "val", views=False)))
    blended = faint_blend(scene.gaussians.means, scene.gaussians.opacities().reshape(-1),
                          plain.encode_gaussians(scene.gaussians), 8)
    assert not np.allclose(blended, plain.encode_gaussians(scene.gaussians), atol=1e-4)
    single, _ = make_predictor(BenchConfig(dataset=data, run=run, faint_neighbours=8))
    np.testing.assert_allclose(single.encode(scene), blended, atol=1e-5)
    pair, _ = make_predictor(BenchConfig(dataset=data, run=run, ensemble_runs=(run,), faint_neighbours=8))
    np.testing.assert_allclose(pair.encode(scene), np.concatenate([blended, blended], axis=1), atol=1e-5)
    # class offsets were fitted on blended scores: predict takes them with the same blend only, in one line
    bench(8, "--class-offsets")
    offsets = str(tmp_path / "bench8--class-offsets.json")
    assert predict("same.ply", "--class-offsets", offsets, "--faint-neighbours", "8").exit_code == 0
    for k in ("0", "16"):
        refused = predict(f"other{k}.ply", "--class-offsets", offsets, "--faint-neighbours", k)
        error = json.loads(refused.stdout)["error"]
        assert refused.exit_code != 0 and f"--faint-neighbours 8, not {k}" in error and "\n" not in error
        assert not (tmp_path / f"other{k}.ply").exists()


def test_a_reports_blend_reads_as_0_when_off_or_absent(tmp_path):
    from ovgaussian.openvocab.class_offsets import offsets_faint_neighbours

    for name, predictor, want in (("old", {"kind": "model"}, 0), ("one", {"faint_neighbours": 1}, 0),
                                  ("eight", {"faint_neighbours": 8}, 8)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"predictor": predictor}))
        assert offsets_faint_neighbours(tmp_path / f"{name}.json") == want
    (tmp_path / "bad.json").write_text(json.dumps({"predictor": {"faint_neighbours": "8"}}))
    with pytest.raises(ValueError, match="bad.json: predictor.faint_neighbours must be a non-negative integer"):
        offsets_faint_neighbours(tmp_path / "bad.json")


def test_calibrated_stacking_scores_its_calibration_run_with_the_same_blend(monkeypatch):
    """Gamma is chosen on the calibration run's scores: with ``--faint-neighbours`` they are blended as the main
    run's are, or the gamma would be fitted on other scores than it is applied to."""
    from pathlib import Path

    from ovgaussian.bench import evaluate
    from ovgaussian.bench.config import BenchConfig

    seen = {}

    def fake_load(run, *args, **kwargs):
        seen.update(kwargs, run=run)
        return "calibrator"

    monkeypatch.setattr(evaluate, "read_json", lambda path: {"train": {"data": {"holdout_classes": ["chair"]}}})
    monkeypatch.setattr(evaluate, "load_model_predictor", fake_load)
    monkeypatch.setattr(evaluate, "calibrate", lambda predictor, scenes, vocabulary, holdout: (predictor, holdout))
    monkeypatch.setattr(evaluate, "_train_scenes", lambda config: [])
    config = BenchConfig(stacking_run=Path("calibration"), faint_neighbours=8)
    assert evaluate.calibrate_stacking(config) == ("calibrator", ("chair",))
    assert seen["faint_neighbours"] == 8 and seen["run"] == Path("calibration")
