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

    # the same through predict's interface: Gaussians and free-text names
    encode_gaussians = encode

    def score_names(self, vectors, names):
        return self.classify(vectors, np.arange(len(names)))


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
    names = ["a", "b", "c"]  # predict's path: encode_gaussians and score_names
    np.testing.assert_array_equal(ensemble.encode_gaussians(scene), vectors)
    want = np.mean([m.score_names(blend @ m.encode_gaussians(scene), names) for m in members], axis=0)
    np.testing.assert_allclose(ensemble.score_names(blend @ vectors, names), want, rtol=1e-5, atol=1e-6)
    for member, trained in zip(members, (("a", "b"), ("a", "b", "c"), ("b", "a"))):
        member.trained_names = frozenset(trained)
    assert ensemble.trained_names == {"a", "b"}  # stacking lowers what every member was trained on
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


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """Shards of two scenes and two one-epoch runs on them, seeds 0 and 1: (folder, data, run0, run1)."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from test_train import _write_shards, make_scene

    tmp_path = tmp_path_factory.mktemp("ensemble")
    data = tmp_path / "data"
    _write_shards(data, [make_scene(s, per_box=20, views=2) for s in range(2)])
    for seed in (0, 1):
        trained = CliRunner().invoke(main, ["train", "--data", str(data), "--epochs", "1", "--model-preset", "slim",
                                            "--pixels-per-view", "64", "--batch-scenes", "2", "--no-progress",
                                            "--seed", str(seed), "--out", str(tmp_path / f"run{seed}")])
        assert trained.exit_code == 0, trained.output
    return tmp_path, data, tmp_path / "run0", tmp_path / "run1"


def test_bench_scores_an_ensemble_of_runs(two_runs):
    """End to end on shards: ``ovgaussian bench --ensemble-run`` records every member's checkpoint; an ensemble of a
    run with itself scores what the run alone scores; one with a second seed is scored; with --stacking-run or a
    baseline predictor it is a one-line error."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main

    tmp_path, data, _, _ = two_runs
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


def test_predict_labels_with_an_ensemble_and_refuses_offsets_of_other_runs(two_runs, tmp_path):
    """``ovgaussian predict --ensemble-run``: the labels are the argmax of the members' mean scores; a run with
    itself labels as the run alone; class offsets of a bench report are taken only with the runs that report
    scored (by checkpoint sha256), else a one-line error; with --stacking-gamma it is refused."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from ovgaussian.predict.query import load_model_predictor
    from seggaussian.io.formats import write_gaussians
    from test_train import make_scene

    _, data, run0, run1 = two_runs
    gaussians = make_scene(5, per_box=20, views=1).gaussians
    scene = tmp_path / "scene.ply"
    write_gaussians(scene, gaussians, "ply")
    names = ("chair", "table", "floor", "wall", "sofa")

    def predict(out, *extra, ok=True):
        result = CliRunner().invoke(main, ["predict", str(scene), "--run", str(run0), "--vocab", ", ".join(names),
                                           "--out", str(tmp_path / out), "--json", *extra])
        assert (result.exit_code == 0) == ok, result.output
        return json.loads(result.stdout)

    def labels(out):
        from plyfile import PlyData

        return np.asarray(PlyData.read(str(tmp_path / out))["vertex"]["semantic"])

    alone = predict("alone.ply")
    doubled = predict("doubled.ply", "--ensemble-run", str(run0))
    mixed = predict("mixed.ply", "--ensemble-run", str(run1))
    np.testing.assert_array_equal(labels("doubled.ply"), labels("alone.ply"))
    members = [load_model_predictor(run) for run in (run0, run1)]
    scores = np.mean([m.score_names(m.encode_gaussians(gaussians), names) for m in members], axis=0)
    want = scores.argmax(axis=1)
    margin = np.sort(scores, axis=1)
    clear = margin[:, -1] - margin[:, -2] > 1e-5  # float ties may break either way
    np.testing.assert_array_equal(labels("mixed.ply")[clear], want[clear])
    assert [m["run"] for m in mixed["ensemble"]] == [str(run1)] and alone["ensemble"] == []

    common = ["bench", "--data", str(data), "--run", str(run0), "--dim", "3d", "--metric", "CSA", "--no-progress",
              "--class-offsets"]
    for out, extra in (("single.json", []), ("pair.json", ["--ensemble-run", str(run1)])):
        result = CliRunner().invoke(main, common + extra + ["--out", str(tmp_path / out)])
        assert result.exit_code == 0, result.output
    predict("with-pair.ply", "--ensemble-run", str(run1), "--class-offsets", str(tmp_path / "pair.json"))
    predict("with-single.ply", "--class-offsets", str(tmp_path / "single.json"))
    for extra, report in (([], "pair.json"), (["--ensemble-run", str(run1)], "single.json")):
        bad = predict("bad.ply", *extra, "--class-offsets", str(tmp_path / report), ok=False)
        assert str(tmp_path / report) in bad["error"] and "give the runs that bench scored" in bad["error"]
        assert "\n" not in bad["error"]
    assert not (tmp_path / "bad.ply").exists()
    bad = predict("bad.ply", "--ensemble-run", str(run1), "--stacking-gamma", "0.1", ok=False)
    assert "not supported" in bad["error"]


def _stub_text_embeddings(device):
    """``text_embeddings(names)`` for a predictor without a text encoder: a fixed unit vector per name (seeded by
    the name), 12 wide as ``test_train.text_stub``."""
    import zlib

    import torch

    def embeddings(names):
        rows = [torch.randn(12, generator=torch.Generator().manual_seed(zlib.crc32(n.encode()))) for n in names]
        return torch.nn.functional.normalize(torch.stack(rows), dim=1).to(device)

    return embeddings


@pytest.fixture(scope="module")
def stub_text_runs(tmp_path_factory):
    """Two one-epoch runs trained with stub text embeddings (no text encoder, which a GPU machine may lack), seeds 0
    and 1: (data, run0, run1)."""
    from ovgaussian.run.config import DataConfig
    from ovgaussian.train.loop import train
    from test_train import _write_shards, make_scene, text_stub, tiny_config, tiny_model_config

    tmp_path = tmp_path_factory.mktemp("stub-text")
    data = tmp_path / "data"
    _write_shards(data, [make_scene(s, per_box=20, views=2) for s in range(2)])
    for seed in (0, 1):
        train(tiny_config(tmp_path / f"run{seed}", 1, seed=seed, data=DataConfig(dataset=data, blend_top_k=8,
                                                                                  pixels_per_view=64)),
              model_config=tiny_model_config(12), text_embeddings=text_stub())
    return data, tmp_path / "run0", tmp_path / "run1"


def _stub_ensemble(runs, device):
    from ovgaussian.predict.query import load_model_predictor

    members = [load_model_predictor(run, device=device) for run in runs]
    for member in members:
        member.text_embeddings = _stub_text_embeddings(device)
    return EnsemblePredictor(members, [m.model.config.semantic_width for m in members])


@pytest.mark.cuda
@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs CUDA (no GPU on this machine)")
def test_bench_and_predict_of_an_ensemble_on_cuda_follow_the_cpu(stub_text_runs):
    """The same two-run ensemble scored (``run_bench``) and applied (``label_gaussians``) with its members on the GPU:
    the bench's 2D score and predict's per-Gaussian scores and labels are the CPU's (labels compared where the CPU's top two scores
    are apart)."""
    from ovgaussian.bench.config import BenchConfig
    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.predict.config import PredictConfig
    from ovgaussian.predict.query import label_gaussians
    from test_train import make_scene

    data, run0, run1 = stub_text_runs
    gaussians = make_scene(5, per_box=20, views=1).gaussians
    names = ("chair", "table", "floor", "wall", "sofa")
    rows, labels, scores = {}, {}, {}
    for device in ("cpu", "cuda"):
        ensemble = _stub_ensemble((run0, run1), device)
        config = BenchConfig(dataset=data, run=run0, metrics=("NVA",), dims=("2d",), max_views_per_scene=1,
                             progress=False, device=device)  # the test shards hold a train split only
        rows[device] = run_bench(config, predictor=ensemble).payload["row"]
        labels[device] = label_gaussians(ensemble, gaussians, PredictConfig(vocabulary=names, device=device)).labels
        scores[device] = ensemble.score_names(ensemble.encode_gaussians(gaussians), names)
    assert rows["cuda"]["2d_NVA"] is not None
    assert rows["cuda"]["2d_NVA"] == pytest.approx(rows["cpu"]["2d_NVA"], abs=5e-3), rows
    np.testing.assert_allclose(scores["cuda"], scores["cpu"], atol=1e-4)
    top = np.sort(scores["cpu"], axis=1)
    clear = top[:, -1] - top[:, -2] > 1e-4
    assert clear.mean() > 0.5
    np.testing.assert_array_equal(labels["cuda"][clear], labels["cpu"][clear])
