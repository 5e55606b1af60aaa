"""Per-class score offsets: exact moves, the exhaustive reference, the protocol (no unseen label read)."""

from __future__ import annotations

import numpy as np
import pytest

from ovgaussian.metrics import confusion_matrix
from ovgaussian.openvocab.class_offsets import (
    OffsetPredictor, fit_class_offsets, fit_offsets, pooled_miou, reference_fit_class_offsets,
)
from ovgaussian.text.vocabulary import benchmark_vocabulary, training_vocabulary
from seggaussian.core.constants import IGNORE_LABEL, UNSEEN_CLASSES, read_class_names
from test_open_vocab import _ClassScorePredictor, _Gaussians, _scenes

NAMES = read_class_names()


def _miou_of(scores, labels, offsets):
    predicted = np.argmax(np.asarray(scores, np.float32) + np.asarray(offsets, np.float32)[None, :], axis=1)
    return pooled_miou(confusion_matrix(predicted, labels, scores.shape[1]))


def _biased_scores(rng, rows=4000, num=4, bias=(0.0, 0.0, 0.12, 0.0)):
    """Noisy one-hot scores with a constant added to some columns: the offsets should take it back."""
    labels = rng.choice(num, rows, p=[0.55, 0.25, 0.1, 0.1])
    scores = rng.normal(0.0, 0.1, (rows, num)).astype(np.float32)
    scores[np.arange(rows), labels] += 0.3
    return (scores + np.asarray(bias, np.float32)[None, :]).astype(np.float32), labels


@pytest.mark.parametrize("seed", range(3))
def test_offsets_are_exact_moves_and_never_lower_the_training_miou(seed):
    rng = np.random.default_rng(seed)
    scores, labels = _biased_scores(rng)
    offsets, before, after = fit_class_offsets(scores, labels, np.ones(4, bool))
    assert before == pytest.approx(_miou_of(scores, labels, np.zeros(4)), abs=0)
    assert after == pytest.approx(_miou_of(scores, labels, offsets), abs=0)  # the argmax, ties as np.argmax
    assert after > before + 0.01  # the bias of column 2 costs mIoU; the offsets win it back
    assert float(offsets[2] - np.median(offsets)) < -0.05
    again, _, _ = fit_class_offsets(scores, labels, np.ones(4, bool))
    assert np.array_equal(again, offsets)


def test_offsets_of_unfitted_columns_stay_zero():
    rng = np.random.default_rng(5)
    scores, labels = _biased_scores(rng, bias=(0.0, 0.0, 0.0, 0.0))
    fitted = np.array([True, True, False, True])
    offsets, before, after = fit_class_offsets(scores, labels, fitted)
    assert offsets[2] == 0.0 and bool((offsets[fitted] != 0).any())
    assert before <= after


@pytest.mark.parametrize("seed", range(3))
def test_one_free_offset_matches_the_exhaustive_reference(seed):
    rng = np.random.default_rng(seed)
    labels = rng.choice(2, 60, p=[0.7, 0.3])
    scores = rng.normal(0.0, 0.1, (60, 2)).astype(np.float32)
    scores[np.arange(60), labels] += 0.08
    scores[:, 1] += 0.05
    grid = [round(0.01 * k, 2) for k in range(-20, 21)]
    _, reference = reference_fit_class_offsets(scores.tolist(), labels.tolist(), grid)
    offsets, _, after = fit_class_offsets(scores, labels, np.array([False, True]))
    assert after >= reference - 1e-12  # the first sweep is that grid; later sweeps only refine it
    assert after == pytest.approx(_miou_of(scores, labels, offsets), abs=0)


def test_bad_scores_and_labels_are_errors():
    with pytest.raises(ValueError, match="NaN"):
        fit_class_offsets(np.array([[np.nan, 0.0]], np.float32), np.array([0]), np.ones(2, bool))
    with pytest.raises(ValueError, match="labels"):
        fit_class_offsets(np.zeros((2, 2), np.float32), np.array([0, 2]), np.ones(2, bool))


def test_offsets_are_fitted_without_reading_unseen_labels():
    rng = np.random.default_rng(0)
    vocabulary = training_vocabulary(20)
    scenes = _scenes(rng, [NAMES.index(vocabulary.names[3])])
    full = fit_offsets(_ClassScorePredictor(), scenes, vocabulary)
    unseen_ids = [NAMES.index(u) for u in UNSEEN_CLASSES]
    removed = [s._replace(gaussians=_Gaussians({"semantic": np.where(np.isin(s.gaussians.extras["semantic"], unseen_ids),
                                                                      IGNORE_LABEL, s.gaussians.extras["semantic"])}))
               for s in scenes]
    assert fit_offsets(_ClassScorePredictor(), removed, vocabulary) == full
    assert full.names == tuple(vocabulary.names) and not set(full.names) & set(UNSEEN_CLASSES)
    assert full.train_miou_after >= full.train_miou_before
    with pytest.raises(ValueError, match="unseen"):
        fit_offsets(_ClassScorePredictor(), scenes, benchmark_vocabulary(20))


def test_offset_predictor_shifts_the_named_classes_only():
    vectors = np.zeros((2, len(NAMES)), np.float32)
    predictor = OffsetPredictor(_ClassScorePredictor(), {NAMES[3]: 0.5, "not a class": 9.0})
    scores = predictor.classify(vectors, np.array([3, 7]))
    assert scores.tolist() == [[0.5, 0.0], [0.5, 0.0]]
    assert predictor.name == "stand-in+offsets"


def test_bench_fits_records_and_applies_the_offsets(tmp_path):
    """End to end on shards: ``ovgaussian bench --class-offsets`` fits the offsets on the train split, records them
    and scores with them; with --stacking-run it is a one-line error."""
    import json

    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from test_train import _write_shards, make_scene

    data = tmp_path / "data"
    _write_shards(data, [make_scene(s, per_box=20, views=2) for s in range(2)])
    trained = CliRunner().invoke(main, ["train", "--data", str(data), "--epochs", "1", "--model-preset", "slim",
                                        "--pixels-per-view", "64", "--batch-scenes", "2", "--no-progress",
                                        "--out", str(tmp_path / "run")])
    assert trained.exit_code == 0, trained.output
    common = ["bench", "--data", str(data), "--run", str(tmp_path / "run"), "--dim", "2d", "--metric", "NVA",
              "--max-views", "1", "--no-progress"]  # every test scene is a train scene: NVA scores its novel views
    result = CliRunner().invoke(main, common + ["--class-offsets", "--out", str(tmp_path / "with.json")])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "with.json").read_text())
    offsets = report["predictor"]["class_offsets"]
    assert offsets["split"] == "train" and not set(offsets["names"]) & set(UNSEEN_CLASSES)
    assert len(offsets["offsets"]) == len(offsets["names"]) and offsets["num_scenes"] >= 1
    assert offsets["train_miou_after"] >= offsets["train_miou_before"]
    assert report["row"]["2d_NVA"] is not None
    bad = CliRunner().invoke(main, common + ["--class-offsets", "--stacking-run", str(tmp_path / "run")])
    assert bad.exit_code != 0 and "not supported" in bad.output and "Traceback" not in bad.output


def test_bench_out_is_a_file_path_a_rerun_replaces(tmp_path):
    """``ovgaussian bench --out`` names the JSON report: a second run to the same path replaces it (make demo run
    twice in one folder failed here with 'Directory ... is a file'); an existing folder is a one-line error."""
    import json

    from click.testing import CliRunner

    from cli.ovgaussian_cli import main
    from test_train import _write_shards, make_scene

    data = tmp_path / "data"
    _write_shards(data, [make_scene(s, per_box=20, views=2) for s in range(2)])
    out = tmp_path / "bench.json"
    common = ["bench", "--data", str(data), "--predictor", "majority", "--dim", "3d", "--no-progress"]
    for _ in range(2):
        result = CliRunner().invoke(main, common + ["--out", str(out)])
        assert result.exit_code == 0, result.output
        assert json.loads(out.read_text())["row"]
    (tmp_path / "folder").mkdir()
    bad = CliRunner().invoke(main, common + ["--out", str(tmp_path / "folder")])
    assert bad.exit_code != 0 and "folder" in bad.output and "Traceback" not in bad.output
