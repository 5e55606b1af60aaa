"""The viewer's relevancy calibration: the offset softmax against its slow reference, the IoU curve and the
offset fit against brute force, and the run's cached calibration (fitted on the train rooms, refitted when its
key changes, offsets 0 when the rooms cannot be read)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ovgaussian.view.calibration import (CALIBRATION_NAME, OFFSET_MAX, OFFSET_MIN, best_offset, fit_offsets,
                                         iou_curve, iou_curve_reference, offset_grid, run_calibration)
from ovgaussian.view.relevancy import (CANONICAL_NEGATIVES, calibrated_relevancy, calibrated_relevancy_reference,
                                       competitor_mask, query_offsets)


def test_offsets_lower_the_query_logit_and_move_the_default_to_sigmoid_of_the_offset():
    rng = np.random.default_rng(3)
    q = rng.normal(0.2, 0.1, (41, 2)).astype(np.float32)
    comp = rng.normal(0.2, 0.1, (41, 5)).astype(np.float32)
    mask = competitor_mask(("chair", "wall"), ("wall", "floor", "chair", "object", "stuff"))
    offsets = np.array([0.7, -0.4], np.float32)
    got = calibrated_relevancy(q, comp, mask, 0.07, offsets, chunk_rows=6)
    np.testing.assert_allclose(got, calibrated_relevancy_reference(q, comp, mask, 0.07, offsets), atol=1e-5)
    # relevancy >= 0.5 with offset d  <=>  the plain softmax probability >= sigmoid(d)
    plain = calibrated_relevancy_reference(q, comp, mask, 0.07)
    for j, d in enumerate(offsets):
        far = np.abs(plain[:, j] - 1 / (1 + math.exp(-d))) > 1e-4  # away from the boundary (float32 rounding)
        assert np.array_equal((got[:, j] >= 0.5)[far], (plain[:, j] >= 1 / (1 + math.exp(-d)))[far])
    # a larger offset never raises the relevancy; huge offsets stay finite, in [0, 1]
    assert np.all(calibrated_relevancy(q, comp, mask, 0.07, offsets + 0.5) <= got + 1e-7)
    extreme = calibrated_relevancy(q, comp, mask, 0.07, np.array([1e4, -1e4], np.float32))
    assert np.isfinite(extreme).all() and extreme[:, 0].max() == 0.0 and extreme[:, 1].min() > 0.999
    with pytest.raises(ValueError, match="offsets"):
        calibrated_relevancy(q, comp, mask, 0.07, np.array([0.0, np.nan]))
    # offsets by name: case and spacing ignored, 0 for a phrase without one
    np.testing.assert_array_equal(query_offsets(("Office  Chair", "lamp"), {"office chair": 0.25}), [0.25, 0.0])


def test_iou_curve_matches_brute_force_with_ties_and_empty_masks():
    rng = np.random.default_rng(0)
    p = np.round(rng.random(300), 2).astype(np.float32)  # many ties
    truth = rng.random(300) < 0.2
    thresholds = np.array([0.0, 0.1, 0.25, 0.5, 0.77, 0.99, 1.5])
    np.testing.assert_allclose(iou_curve(p, truth, thresholds), iou_curve_reference(p, truth, thresholds))
    np.testing.assert_allclose(iou_curve(p, np.zeros(300, bool), [2.0]), [0.0])  # nothing on either side


def _reference_fit(rooms, num_names, min_gaussians):
    """Brute force: every grid offset, every room's IoU mask by mask; ties to the offset nearest 0."""
    grid = offset_grid()
    out = []
    for v in range(num_names):
        used = [(p[:, v], t == v) for p, t in rooms if np.count_nonzero(t == v) >= min_gaussians]
        if not used:
            out.append(0.0)
            continue
        means = [np.mean([iou_curve_reference(p, t, [1 / (1 + math.exp(-d))])[0] for p, t in used]) for d in grid]
        top = max(means)
        out.append(min((d for d, m in zip(grid, means) if m == top), key=lambda d: (abs(d), d)))
    return out


def test_fit_offsets_matches_brute_force_and_finds_each_classs_operating_point():
    rng = np.random.default_rng(5)
    rooms = []
    for _ in range(3):
        n = 400
        truth = rng.integers(-1, 3, n)
        p = rng.random((n, 3)).astype(np.float32) * 0.3
        # name 0: its Gaussians at 0.28-0.45 (below the plain 0.5); name 1: others up to 0.85, its own above 0.9
        p[truth == 0, 0] = rng.uniform(0.28, 0.45, np.count_nonzero(truth == 0))
        p[:, 1] = rng.uniform(0.0, 0.85, n)
        p[truth == 1, 1] = rng.uniform(0.9, 0.99, np.count_nonzero(truth == 1))
        truth[truth == 2] = -1  # name 2 never in a room: offset 0
        rooms.append((p, truth))
    fits = fit_offsets(rooms, 3, min_gaussians=20)
    assert [f.offset for f in fits] == pytest.approx(_reference_fit(rooms, 3, 20))
    assert fits[0].offset == pytest.approx(OFFSET_MIN)  # wanted 0.28 < 1/3: held at the bound
    assert 0.85 <= 1 / (1 + math.exp(-fits[1].offset)) <= 0.9 and fits[1].iou_at_offset == pytest.approx(1.0)
    assert fits[1].iou_at_offset > fits[1].iou_at_zero and fits[1].rooms == 3
    assert (fits[2].offset, fits[2].rooms, fits[2].iou_at_zero) == (0.0, 0, None)
    # a room with too few Gaussians of a name takes no part in its fit
    assert fit_offsets(rooms[:1], 3, min_gaussians=10_000)[1].offset == 0.0


def test_offset_grid_and_ties():
    grid = offset_grid()
    assert grid[0] == pytest.approx(OFFSET_MIN) and grid[-1] <= OFFSET_MAX and 0.0 in grid
    assert np.all(np.diff(grid) > 0)
    flat = np.ones((2, len(grid)))
    assert best_offset(flat, grid) == 0.0


class _Counting:
    """A predictor wrapper counting the rooms it encodes."""

    def __init__(self, inner):
        self.inner, self.encoded = inner, 0

    def encode_gaussians(self, gaussians):
        self.encoded += 1
        return self.inner.encode_gaussians(gaussians)

    def decode(self, vectors):
        return self.inner.decode(vectors)

    def text_embeddings(self, names):
        return self.inner.text_embeddings(names)


def test_run_calibration_fits_on_the_train_rooms_caches_and_falls_back(tmp_path):
    from test_bench import _write_tiny_dataset
    from test_view import TextOracle, needs_text_encoder

    needs_text_encoder()
    dataset = _write_tiny_dataset(tmp_path / "tiny")
    vocabulary = ("wall", "floor", "chair", "toilet")  # the train room's classes
    predictor = _Counting(TextOracle(vocabulary))
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {"data": {"dataset": str(dataset), "split": "train"}}}))
    result = run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07)
    assert predictor.encoded == 1 and result.calibration.scenes == ("tr0",)
    # a perfect field separates every class at every threshold of the grid: ties keep 0
    assert result.offsets == {} and result.calibration.rooms == (1, 1, 1, 1)
    assert result.calibration.iou_at_zero == pytest.approx((1.0,) * 4)
    cached = json.loads((run / CALIBRATION_NAME).read_text())
    assert cached["names"] == list(vocabulary) and cached["competitors"][-4:] == list(CANONICAL_NEGATIVES)
    # the same key: read back, nothing encoded
    again = run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07)
    assert predictor.encoded == 1 and again.calibration == result.calibration and "from" in again.note
    # a cached offset is used as written
    cached["offsets"][2] = 0.4
    (run / CALIBRATION_NAME).write_text(json.dumps(cached))
    assert run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07).offsets == {"chair": 0.4}
    # another temperature or negatives: refitted; a broken cache: refitted
    run_calibration(run, predictor, vocabulary, ("object",), 0.07)
    assert predictor.encoded == 2
    (run / CALIBRATION_NAME).write_text("{")
    run_calibration(run, predictor, vocabulary, ("object",), 0.07)
    assert predictor.encoded == 3 and json.loads((run / CALIBRATION_NAME).read_text())["competitors"][-1] == "object"
    # train rooms that cannot be read, or none recorded: offsets 0, said in one line
    (run / "config.json").write_text(json.dumps({"train": {"data": {"dataset": str(tmp_path / "gone")}}}))
    gone = run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07)
    assert gone.offsets == {} and gone.calibration is None and "uncalibrated" in gone.note
    assert "\n" not in gone.note
    # ... unless the viewer's dataset holds them (a moved dataset), or a cached fit of the same model and names exists
    moved = run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07, dataset=dataset)
    assert moved.calibration is not None and moved.calibration.dataset == str(dataset) and predictor.encoded == 4
    kept = run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07)
    assert kept.calibration == moved.calibration and "not readable here" in kept.note and predictor.encoded == 4
    assert "\n" not in kept.note
    (run / "config.json").write_text(json.dumps({"train": {}}))
    assert "no train dataset" in run_calibration(run, predictor, vocabulary, CANONICAL_NEGATIVES, 0.07).note


def test_viewer_state_applies_the_offsets_by_name(oracle_state):
    from ovgaussian.view.state import ViewerState

    shifted = ViewerState(oracle_state.scene, oracle_state.field, oracle_state.vocabulary, oracle_state.negatives,
                          oracle_state.temperature, {"chair": 2.0})
    base = oracle_state.relevancies(("Chair", "table"))
    got = shifted.relevancies(("Chair", "table"))
    np.testing.assert_allclose(got[:, 1], base[:, 1])
    want = calibrated_relevancy(oracle_state.field.scores(("Chair",)), oracle_state.field.scores(shifted.competitors),
                                competitor_mask(("Chair",), shifted.competitors), shifted.temperature,
                                np.array([2.0], np.float32))
    np.testing.assert_allclose(got[:, :1], want, atol=1e-6)
    assert np.all(got[:, 0] <= base[:, 0] + 1e-7)


@pytest.fixture(scope="module")
def oracle_state():
    from test_view import ROOM_CLASSES, TextOracle, needs_text_encoder, room_scene, synthetic_room

    needs_text_encoder()
    from ovgaussian.view.field import QueryField
    from ovgaussian.view.state import ViewerState

    room = synthetic_room(spacing=0.2)
    oracle = TextOracle(ROOM_CLASSES)
    return ViewerState(room_scene(room), QueryField.from_predictor(oracle, oracle.encode_gaussians(room)), ROOM_CLASSES)
