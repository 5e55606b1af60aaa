"""Open vocabulary without image-language weights: calibrated stacking (legal gamma) and prompt ensembles."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest
import torch

from ovgaussian.openvocab.calibration import StackedPredictor, calibrate, choose_gamma, stack_scores
from ovgaussian.text.vocabulary import benchmark_vocabulary, training_vocabulary
from seggaussian.core.constants import IGNORE_LABEL, UNSEEN_CLASSES, read_class_names

NAMES = read_class_names()


class _Gaussians(NamedTuple):
    extras: dict


class _Scene(NamedTuple):
    scene_id: str
    gaussians: _Gaussians
    vectors: np.ndarray


class _ClassScorePredictor:
    """Per-Gaussian vectors are per-top-100-class scores; classify picks the requested classes' columns."""

    name = "stand-in"

    def encode(self, scene):
        return scene.vectors

    def classify(self, vectors, class_ids):
        return vectors[:, np.asarray(class_ids)]


def _scenes(rng, held: list[int], count=3, n=3000):
    """Scenes whose Gaussians belong to benchmark classes (unseen ones included); held-out and unseen classes
    score 0.25 lower on their true class than seen classes do, as for a model trained without them."""
    ids = benchmark_vocabulary(20).class_ids
    scenes = []
    for s in range(count):
        labels = rng.choice(ids, n)
        scores = rng.normal(0.0, 0.1, (n, len(NAMES))).astype(np.float32)
        bonus = np.where(np.isin(labels, held) | np.isin(labels, [NAMES.index(u) for u in UNSEEN_CLASSES]),
                         0.25, 0.5)
        scores[np.arange(n), labels] += bonus
        scenes.append(_Scene(f"s{s}", _Gaussians({"semantic": labels.astype(np.int32)}), scores))
    return scenes


def test_gamma_is_chosen_without_reading_unseen_labels():
    rng = np.random.default_rng(0)
    vocabulary = training_vocabulary(20)
    held_names = vocabulary.names[3:5]
    scenes = _scenes(rng, [NAMES.index(n) for n in held_names])
    full = calibrate(_ClassScorePredictor(), scenes, vocabulary, held_names)
    # the unseen labels removed from the calibration data (IGNORE), and alternatively replaced by noise
    unseen_ids = [NAMES.index(u) for u in UNSEEN_CLASSES]
    removed = [s._replace(gaussians=_Gaussians({"semantic": np.where(np.isin(s.gaussians.extras["semantic"], unseen_ids),
                                                                      IGNORE_LABEL, s.gaussians.extras["semantic"])}))
               for s in scenes]
    assert calibrate(_ClassScorePredictor(), removed, vocabulary, held_names) == full
    assert 0.1 <= full.gamma <= 0.4  # the held-out classes' margin (0.25) is recovered
    assert full.pseudo_unseen_miou > 0.5 and full.seen_miou > 0.5
    assert len(full.curve) == len(full.candidates) and max(full.curve) == full.harmonic_mean
    assert not set(full.classes) & set(UNSEEN_CLASSES)
    with pytest.raises(ValueError, match="unseen"):
        calibrate(_ClassScorePredictor(), scenes, benchmark_vocabulary(20), held_names)
    with pytest.raises(ValueError, match="held-out"):
        calibrate(_ClassScorePredictor(), scenes, vocabulary, ())


def test_choose_gamma_recovers_a_known_margin_and_zero_without_one():
    rng = np.random.default_rng(1)
    n, classes = 4000, 6
    labels = rng.integers(0, classes, n)
    scores = rng.normal(0, 0.05, (n, classes)).astype(np.float32)
    scores[np.arange(n), labels] += 0.3
    held = np.array([4, 5])
    # no margin: gamma 0 is best (ties go to the smallest)
    gamma, h, *_ = choose_gamma(scores, labels, held)
    assert gamma == 0.0 and h > 0.99
    shifted = scores.copy()
    shifted[:, :4] += 0.35  # the kept classes outscore everything by 0.35: the held-out ones never win at gamma 0
    gamma, h, seen, unseen, curve = choose_gamma(shifted, labels, held)
    assert curve[0] < 0.5 and 0.3 <= gamma <= 0.5 and h > 0.9
    assert np.array_equal(np.argmax(stack_scores(shifted, np.arange(6) < 4, gamma), 1), np.argmax(scores, 1))


def test_stacked_predictor_lowers_only_the_seen_classes():
    ids = benchmark_vocabulary(20).class_ids
    vectors = np.zeros((2, len(NAMES)), np.float32)
    out = StackedPredictor(_ClassScorePredictor(), 0.2).classify(vectors, ids)
    unseen = np.array([NAMES[i] in UNSEEN_CLASSES for i in ids])
    assert np.allclose(out[:, unseen], 0.0) and np.allclose(out[:, ~unseen], -0.2)


def test_holdout_classes_leave_the_training_vocabulary():
    full = training_vocabulary(20)
    held = training_vocabulary(20, full.names[:2])
    assert set(held.names) == set(full.names) - set(full.names[:2])
    with pytest.raises(ValueError, match="not seen classes"):
        training_vocabulary(20, ("sofa",))


def test_prompt_ensemble_is_the_renormalized_mean_of_cached_templates(tmp_path, monkeypatch):
    from ovgaussian.text import encoders as text
    from ovgaussian.text.prompt_ensemble import ensemble_text_embeddings
    from ovgaussian.run.config import TextConfig

    calls = []

    def fake_encode(names, config):
        calls.append(config.prompt_template)
        g = torch.Generator().manual_seed(len(config.prompt_template))
        e = torch.randn(len(names), 8, generator=g)
        return e / e.norm(dim=1, keepdim=True)

    monkeypatch.setattr(text, "encode_texts", fake_encode)
    monkeypatch.setattr(text, "encoder_key", lambda config: "fake")
    templates = ("a {name}.", "the {name} here.", "one {name}")
    names = ["chair", "table"]
    out = ensemble_text_embeddings(names, TextConfig(), tmp_path, templates)
    parts = torch.stack([fake_encode(names, TextConfig(prompt_template=t)) for t in templates])
    expected = parts.mean(0) / parts.mean(0).norm(dim=1, keepdim=True)
    assert torch.allclose(out, expected) and torch.allclose(out.norm(dim=1), torch.ones(2))
    calls.clear()
    again = ensemble_text_embeddings(names, TextConfig(), tmp_path, templates)
    assert torch.equal(again, out) and calls == []  # every template's embeddings came from the cache
    assert len(list(tmp_path.glob("text_*.safetensors"))) == len(templates)


def test_generator_synthesizes_unseen_features_with_the_right_statistics(one_torch_thread):
    """Toy ZS3Net case: class c's features ~ N(A t_c, S S^T) with text embedding t_c. Trained on 20 seen classes,
    the generator's features of 4 held-back classes (their text only) have the right mean and covariance:
    mean within 0.2 x the spread of the class means, covariance within 25% (Frobenius; measured: <= 0.10, <= 0.10)."""
    from ovgaussian.openvocab.config import SynthesisConfig
    from ovgaussian.openvocab.feature_synthesis import synthesize, train_classifier, train_generator

    g = torch.Generator().manual_seed(0)
    text_width, width, seen, unseen, per_class = 6, 4, 20, 4, 400
    text = torch.randn(seen + unseen, text_width, generator=g)
    text = text / text.norm(dim=1, keepdim=True)
    A = torch.randn(width, text_width, generator=g)
    S = 0.3 * torch.randn(width, width, generator=g)
    cov = S @ S.T
    labels = torch.arange(seen).repeat_interleave(per_class)
    feats = text[labels] @ A.T + torch.randn(labels.numel(), width, generator=g) @ S.T
    config = SynthesisConfig(generator_steps=600, classes_per_step=8, samples_per_class=128, hidden_width=128,
                             noise_width=8, learning_rate=3e-3, classifier_steps=300)
    gen, scale = train_generator(text[:seen], feats, labels, config)
    spread = (text[labels] @ A.T).std(0).mean()  # how far apart class means are
    for c in range(seen, seen + unseen):
        fake = synthesize(gen, scale, text[c:c + 1], 4000, seed=c)
        mean_error = (fake.mean(0) - A @ text[c]).norm()
        cov_error = (torch.cov(fake.T) - cov).norm() / cov.norm()
        assert mean_error < 0.2 * spread, (c, float(mean_error), float(spread))
        assert cov_error < 0.25, (c, float(cov_error))
    # a classifier trained on real seen + synthetic unseen features recognizes real unseen features
    synthetic = synthesize(gen, scale, text[seen:], per_class, seed=99)
    all_labels = torch.cat([labels, torch.arange(seen, seen + unseen).repeat_interleave(per_class)])
    classifier = train_classifier(torch.cat([feats, synthetic]), all_labels, seen + unseen, config)
    test_labels = torch.arange(seen, seen + unseen).repeat_interleave(200)
    test = text[test_labels] @ A.T + torch.randn(test_labels.numel(), width, generator=g) @ S.T
    accuracy = (classifier.logits(test).argmax(1) == test_labels).float().mean()
    assert accuracy > 0.4  # measured 0.62; chance among 24 classes: 0.04


@pytest.mark.parametrize("case", ["random", "identical", "far apart", "one far row"])
def test_mmd2_matches_the_pairwise_reference_forward_and_backward(case):
    """The Gram-form, batched MMD against the float64 pair-by-pair sum: value and both input gradients, on a
    batch of 3 pairs; degenerate cases: identical samples (MMD 0, zero distances on the diagonal), samples so far
    apart that every cross kernel underflows (the exponent floor), one far outlier row."""
    from ovgaussian.openvocab.feature_synthesis import mmd2, mmd2_reference

    g = torch.Generator().manual_seed(3)
    bandwidths = (0.25, 0.5, 1.0, 2.0, 4.0)
    x = torch.randn(3, 17, 9, generator=g)
    y = torch.randn(3, 13, 9, generator=g) + 0.5
    if case == "identical":
        y = x.clone()
    elif case == "far apart":
        y = y + 300.0
    elif case == "one far row":
        x[:, 4] += 500.0
    x.requires_grad_(True)
    y.requires_grad_(True)
    fast = mmd2(x, y, bandwidths)
    assert fast.shape == (3,) and torch.isfinite(fast).all()
    fast.sum().backward()
    for b in range(3):
        xb = x.detach()[b].clone().requires_grad_(True)
        yb = y.detach()[b].clone().requires_grad_(True)
        slow = mmd2_reference(xb, yb, bandwidths)
        slow.backward()
        # float32 Gram form: exact to 1e-5 about the samples' mean; an outlier 500 away pulls the mean by 30, so
        # the other rows' distances carry ~eps * 30^2 (measured 0.7 % of the MMD)
        tolerance = 2e-2 if case == "one far row" else 1e-5
        assert abs(float(fast[b]) - float(slow)) < tolerance * max(1.0, abs(float(slow))), (b, float(fast[b]),
                                                                                            float(slow))
        assert torch.allclose(x.grad[b], xb.grad, atol=tolerance), b
        assert torch.allclose(y.grad[b], yb.grad, atol=tolerance), b
    if case == "identical":
        assert torch.allclose(fast, torch.zeros(3), atol=1e-5)
    if case == "far apart":  # no cross term: each sample set's own kernel mean, summed
        assert (fast > 1.0).all()


class _ScoreStub:
    """A predictor for ``label_gaussians``: trained on chair and table; every Gaussian scores chair 0.5, table 0.1,
    sofa 0.4 (names in that order)."""

    trained_names = frozenset({"chair", "table"})

    def encode_gaussians(self, gaussians):
        return np.zeros((len(gaussians), 3), np.float32)

    def score_names(self, vectors, names):
        return np.tile(np.array([[0.5, 0.1, 0.4]], np.float32), (len(vectors), 1))


def _four_gaussians():
    from seggaussian.core.gaussians import Gaussians

    n = 4
    return Gaussians.from_arrays(np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros((n, 3)), np.zeros(n),
                                 np.zeros((n, 1, 3)))


def test_predict_stacking_gamma_lowers_the_trained_names_only():
    from ovgaussian.predict.query import label_gaussians
    from ovgaussian.predict.config import PredictConfig

    gaussians = _four_gaussians()
    names = ("chair", "table", "sofa")
    plain = label_gaussians(_ScoreStub(), gaussians, PredictConfig(vocabulary=names))
    stacked = label_gaussians(_ScoreStub(), gaussians, PredictConfig(vocabulary=names, stacking_gamma=0.2))
    assert set(plain.labels.tolist()) == {0} and set(stacked.labels.tolist()) == {2}


def test_predict_adds_the_class_offsets_of_a_bench_report(tmp_path):
    """``--class-offsets REPORT``: the offsets a bench recorded move the scores of those names (others keep 0); a
    report without them, a broken file and offsets with a stacking gamma are refused in one line."""
    import json

    from ovgaussian.openvocab.class_offsets import offsets_checkpoints, read_class_offsets
    from ovgaussian.predict.config import PredictConfig
    from ovgaussian.predict.query import label_gaussians

    report = tmp_path / "bench-K20.json"
    report.write_text(json.dumps({"predictor": {"kind": "model", "class_offsets": {
        "names": ["chair", "sofa", "lamp"], "offsets": [-0.05, 0.2, 1.0], "train_miou_before": 0.3}}}))
    offsets = read_class_offsets(report)
    assert offsets == {"chair": -0.05, "sofa": 0.2, "lamp": 1.0}
    gaussians = _four_gaussians()
    names = ("chair", "table", "sofa")
    plain = label_gaussians(_ScoreStub(), gaussians, PredictConfig(vocabulary=names))
    moved = label_gaussians(_ScoreStub(), gaussians, PredictConfig(vocabulary=names), class_offsets=offsets)
    assert set(plain.labels.tolist()) == {0} and set(moved.labels.tolist()) == {2}  # 0.45 < 0.6: sofa
    with pytest.raises(ValueError, match="stacking gamma"):
        label_gaussians(_ScoreStub(), gaussians, PredictConfig(vocabulary=names, stacking_gamma=0.1), class_offsets=offsets)
    (tmp_path / "plain.json").write_text(json.dumps({"predictor": {"kind": "model"}}))
    (tmp_path / "broken.json").write_text("{")
    (tmp_path / "nan.json").write_text('{"predictor": {"class_offsets": {"names": ["a"], "offsets": [NaN]}}}')
    assert offsets_checkpoints(report) == ()  # no checkpoint recorded: nothing to compare
    (tmp_path / "pair.json").write_text(json.dumps({"predictor": {"checkpoint_sha256": "a", "ensemble": [
        {"checkpoint_sha256": "b"}]}}))
    assert offsets_checkpoints(tmp_path / "pair.json") == ("a", "b")
    (tmp_path / "odd.json").write_text('{"predictor": "model"}')
    (tmp_path / "list.json").write_text('[1, 2]')
    for name, message in (("plain.json", "no predictor.class_offsets"), ("broken.json", "not a JSON"),
                          ("odd.json", "no predictor.class_offsets"), ("list.json", "no predictor.class_offsets"),
                          ("nan.json", "finite"), ("missing.json", "cannot read")):
        with pytest.raises(ValueError, match=message) as err:
            read_class_offsets(tmp_path / name)
        assert str(tmp_path / name) in str(err.value) and "\n" not in str(err.value)


def test_bench_scores_each_method_and_records_the_calibration(tmp_path):
    """End to end on shards: a run, a calibration run with a held-out class, bench with stacking + generative."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.bench.config import BenchConfig
    from ovgaussian.openvocab.config import SynthesisConfig
    from test_train import _write_shards, make_scene

    data = tmp_path / "data"
    _write_shards(data, [make_scene(s, per_box=20, views=2) for s in range(2)])
    common = ["train", "--data", str(data), "--epochs", "1", "--model-preset", "slim", "--pixels-per-view", "64",
              "--batch-scenes", "2", "--no-progress"]
    for out, extra in (("run", []), ("calrun", ["--holdout-classes", "table"])):
        result = CliRunner().invoke(main, common + ["--out", str(tmp_path / out)] + extra)
        assert result.exit_code == 0, result.output
    bad = CliRunner().invoke(main, ["bench", "--data", str(data), "--run", str(tmp_path / "run"), "--stacking-run",
                                    str(tmp_path / "run"), "--metric", "NVA", "--dim", "2d", "--no-progress"])
    assert bad.exit_code != 0 and "not a calibration run" in bad.output and "Traceback" not in bad.output
    config = BenchConfig(dataset=data, run=tmp_path / "run", metrics=("NVA",), dims=("2d",), max_views_per_scene=1,
                         progress=False, generative=True, stacking_run=tmp_path / "calrun",
                         synthesis=SynthesisConfig(generator_steps=20, samples_per_class=32, real_per_class=200,
                                                   synthetic_per_class=100, classifier_steps=20))
    report = run_bench(config)
    predictor = report.payload["predictor"]
    stacking = predictor["stacking"]
    assert stacking["pseudo_unseen"] == ["table"] and stacking["gamma"] in stacking["candidates"]
    assert stacking["split"] == "train" and not set(stacking["classes"]) & set(UNSEEN_CLASSES)
    from ovgaussian.run.checkpoint import latest_checkpoint, weights_sha256
    assert stacking["checkpoint_sha256"] == weights_sha256(latest_checkpoint(tmp_path / "calrun")) is not None
    assert set(predictor["generative"]["synthesized_classes"]) == set(UNSEEN_CLASSES) & set(benchmark_vocabulary(20).names)
    assert predictor["prompt_templates"] == []  # the prompt ensemble is tested above (each template: one encoder run)
    assert report.payload["row"]["2d_NVA"] is not None
