import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ovgaussian.metrics import (
    unseen_share,
    ConfusionMatrix,
    confusion_matrix,
    confusion_matrix_reference,
    format_class_table,
    miou,
    miou_reference,
    scores_from_confusion,
)
from seggaussian.core.constants import IGNORE_LABEL

I = IGNORE_LABEL


def test_hand_computed_confusion():
    gt = np.array([0, 0, 1, 1, 2, I, 0])
    pred = np.array([0, 1, 1, 1, 0, 2, I])
    cm = confusion_matrix(pred, gt, 4)
    expected = np.zeros((4, 5), np.int64)
    expected[0, 0] = 1
    expected[0, 1] = 1
    expected[1, 1] = 2
    expected[2, 0] = 1
    expected[0, 4] = 1  # unpredicted sample of class 0
    np.testing.assert_array_equal(cm, expected)
    s = scores_from_confusion(cm)
    # class 0: TP 1, FP 1 (the 2 predicted as 0), FN 2 (one as 1, one unpredicted) -> 1/4
    # class 1: TP 2, FP 1, FN 0 -> 2/3; class 2: TP 0, FP 0 (its prediction sits on an ignored sample), FN 1 -> 0
    # class 3: absent everywhere -> NaN
    assert s.iou[0] == pytest.approx(0.25)
    assert s.iou[1] == pytest.approx(2 / 3)
    assert s.iou[2] == 0.0
    assert math.isnan(s.iou[3])
    assert s.miou == pytest.approx((0.25 + 2 / 3 + 0) / 3)
    np.testing.assert_array_equal(s.scored_classes, [0, 1, 2])
    assert s.acc[0] == pytest.approx(1 / 3) and s.acc[1] == 1.0 and s.acc[2] == 0.0 and math.isnan(s.acc[3])
    assert s.num_samples == 6 and s.num_unpredicted == 1


def test_all_right_and_all_wrong():
    gt = np.array([0, 1, 2, 2])
    assert miou(gt, gt, 3) == 1.0
    s = scores_from_confusion(confusion_matrix((gt + 1) % 3, gt, 3))
    assert s.miou == 0.0 and s.macc == 0.0


def test_class_predicted_but_never_present_counts_as_zero():
    gt = np.array([0, 0, 0, 0])
    pred = np.array([0, 0, 0, 1])
    s = scores_from_confusion(confusion_matrix(pred, gt, 3))
    assert s.iou[0] == pytest.approx(0.75)
    assert s.iou[1] == 0.0  # FP only: scored as 0, not NaN
    assert math.isnan(s.iou[2])
    assert s.miou == pytest.approx(0.375)
    assert math.isnan(s.acc[1])  # accuracy undefined for a class with no ground truth
    assert s.macc == pytest.approx(0.75)


def test_nothing_scored_gives_none_not_nan():
    s = scores_from_confusion(confusion_matrix(np.array([I, 0]), np.array([I, I]), 3))
    assert s.miou is None and s.macc is None and s.num_samples == 0
    assert miou(np.zeros(0, np.int64), np.zeros(0, np.int64), 2) is None
    # averaging over classes that are all absent
    s = scores_from_confusion(confusion_matrix(np.array([0]), np.array([0]), 3), classes=[1, 2])
    assert s.miou is None and s.scored_classes.size == 0


def test_subset_mean_uses_full_matrix():
    # OVA-style: predictions among all classes, mean over class 2 only; FP from class 0 counts.
    gt = np.array([0, 0, 2, 2])
    pred = np.array([2, 0, 2, 1])
    s = scores_from_confusion(confusion_matrix(pred, gt, 3), classes=[2])
    assert s.miou == pytest.approx(1 / 3)  # TP 1, FP 1, FN 1


def test_bad_labels_named():
    with pytest.raises(ValueError, match="predicted labels"):
        confusion_matrix(np.array([5]), np.array([0]), 3)
    with pytest.raises(ValueError, match="target labels"):
        confusion_matrix(np.array([0]), np.array([-1]), 3)
    with pytest.raises(TypeError, match="integers"):
        confusion_matrix(np.array([0.0]), np.array([0]), 3)
    with pytest.raises(ValueError, match="shape"):
        confusion_matrix(np.array([0, 1]), np.array([0]), 3)


def test_accumulator_sums_scenes():
    acc = ConfusionMatrix(3)
    acc.update(np.array([0, 1]), np.array([0, 0]))
    acc.update(np.array([[2, 2]]), np.array([[2, I]]))
    np.testing.assert_array_equal(acc.counts, confusion_matrix(np.array([0, 1, 2, 2]), np.array([0, 0, 2, I]), 3))
    table = format_class_table(acc.scores(), ["a", "b", "c"])
    assert "| b | 0.00 | - |" in table and "| c | 100.00 | 100.00 |" in table


labels = st.integers(min_value=0, max_value=5).map(lambda v: I if v == 5 else v)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(labels, labels), max_size=60), st.lists(st.integers(0, 4), max_size=5))
def test_fast_matches_reference(pairs, subset):
    pred = np.array([p for p, _ in pairs], dtype=np.int64)
    gt = np.array([t for _, t in pairs], dtype=np.int64)
    np.testing.assert_array_equal(confusion_matrix(pred, gt, 5), confusion_matrix_reference(pred, gt, 5))
    for classes in (None, subset):
        fast = miou(pred, gt, 5, classes=classes)
        ref = miou_reference(pred, gt, 5, classes=classes)
        if ref is None:
            assert fast is None
        else:
            assert fast == pytest.approx(ref, abs=1e-12)


def test_unseen_share_matches_relabelled_predictions():
    """unseen_right = the mIoU of predictions corrected on the unseen pixels; seen_only = the seen classes'
    mIoU of the pixels that are not unseen; both computed here from edited label arrays."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        k = int(rng.integers(2, 7))
        n = int(rng.integers(1, 60))
        target = rng.integers(0, k, n)
        predicted = rng.integers(0, k, n)
        predicted[rng.random(n) < 0.1] = IGNORE_LABEL  # uncovered pixels
        unseen = rng.choice(k, size=int(rng.integers(1, k)), replace=False)
        seen = np.setdiff1d(np.arange(k), unseen)
        share = unseen_share(confusion_matrix(predicted, target, k), unseen)
        assert share.as_scored == pytest.approx(miou(predicted, target, k))
        corrected = np.where(np.isin(target, unseen), target, predicted)
        assert share.unseen_right == pytest.approx(miou(corrected, target, k))
        keep = ~np.isin(target, unseen)
        expected = miou(predicted[keep], target[keep], k, classes=seen) if keep.any() else None
        assert share.seen_only == pytest.approx(expected)


def test_unseen_share_by_hand():
    # classes: 0 seen, 1 seen, 2 unseen; all 4 pixels of class 2 are predicted 0.
    predicted = np.array([0, 0, 1, 1, 0, 0, 0, 0])
    target = np.array([0, 0, 1, 1, 2, 2, 2, 2])
    share = unseen_share(confusion_matrix(predicted, target, 3), [2])
    assert share.as_scored == pytest.approx((2 / 6 + 1.0 + 0.0) / 3)
    assert share.unseen_right == pytest.approx(1.0)
    assert share.seen_only == pytest.approx(1.0)
    with pytest.raises(ValueError, match="unseen classes must lie"):
        unseen_share(confusion_matrix(predicted, target, 3), [3])
