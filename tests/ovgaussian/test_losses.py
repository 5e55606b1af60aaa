"""Losses of OVGaussian: hand-computed cases, references, extreme and empty inputs."""

from __future__ import annotations

import math

import pytest
import torch

from ovgaussian.train.losses import (
    combine_losses, compute_text_logits, lovasz_softmax, masked_cosine_loss, masked_cross_entropy,
    partial_label_nll, reference_cosine_loss, reference_cross_entropy, reference_lovasz_softmax,
    reference_text_cross_entropy, text_cross_entropy,
)
from seggaussian.core.constants import IGNORE_LABEL


def test_cross_entropy_hand_computed():
    logits = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    labels = torch.tensor([2, 1, IGNORE_LABEL])
    loss, count = masked_cross_entropy(logits, labels)
    expected = (-(3 - math.log(math.e + math.e ** 2 + math.e ** 3)) + math.log(3)) / 2
    assert count == 2
    assert float(loss) == pytest.approx(expected, rel=1e-6)


def test_text_logits_are_cosines_over_temperature():
    features = torch.tensor([[2.0, 0.0], [0.0, 0.0], [1.0, 1.0]])
    text = torch.tensor([[1.0, 0.0], [0.0, 3.0]])  # not normalized on purpose
    logits = compute_text_logits(features, text, 0.5)
    expected = torch.tensor([[2.0, 0.0], [0.0, 0.0], [math.sqrt(2.0), math.sqrt(2.0)]])
    torch.testing.assert_close(logits, expected)
    loss, _ = masked_cross_entropy(logits[:1], torch.tensor([0]))
    assert float(loss) == pytest.approx(math.log(1 + math.exp(-2.0)), rel=1e-6)
    with pytest.raises(ValueError, match="temperature"):
        compute_text_logits(features, text, 0.0)


@pytest.mark.parametrize("seed", range(3))
def test_cross_entropy_matches_reference(seed):
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(50, 7, generator=g, dtype=torch.float64) * 10
    labels = torch.randint(0, 7, (50,), generator=g)
    labels[torch.rand(50, generator=g) < 0.3] = IGNORE_LABEL
    loss, _ = masked_cross_entropy(logits, labels)
    assert float(loss) == pytest.approx(reference_cross_entropy(logits.tolist(), labels.tolist()), rel=1e-12)


def test_cross_entropy_is_stable_for_extreme_logits():
    logits = torch.tensor([[1e4, -1e4, 0.0], [-1e4, 1e4, 1e4]], requires_grad=True)
    loss, _ = masked_cross_entropy(logits, torch.tensor([1, 0]))
    assert torch.isfinite(loss)
    assert float(loss) == pytest.approx((2e4 + 2e4 + math.log(2)) / 2, rel=1e-6)
    loss.backward()
    assert torch.isfinite(logits.grad).all()
    right, _ = masked_cross_entropy(torch.tensor([[1e4, -1e4]]), torch.tensor([0]))
    assert float(right) == 0.0
    # extreme decoder outputs go through the cosine: logits stay bounded by 1/temperature
    huge = torch.tensor([[1e30, -1e30], [1e-30, 0.0], [0.0, 0.0]], requires_grad=True)
    logits = compute_text_logits(huge, torch.eye(2), 0.07)
    assert logits.abs().max() <= 1 / 0.07 + 1e-4
    l2, _ = masked_cross_entropy(logits, torch.tensor([0, 1, 0]))
    l2.backward()
    assert torch.isfinite(l2) and torch.isfinite(huge.grad).all()


def test_empty_valid_sets_give_zero_not_nan():
    features = torch.randn(4, 3, requires_grad=True)
    logits = compute_text_logits(features, torch.eye(3), 0.1)
    loss, count = masked_cross_entropy(logits, torch.full((4,), IGNORE_LABEL))
    assert count == 0 and float(loss) == 0.0
    loss.backward()
    assert torch.equal(features.grad, torch.zeros_like(features))
    empty, count = masked_cross_entropy(torch.zeros(0, 3, requires_grad=True), torch.zeros(0, dtype=torch.long))
    assert count == 0 and float(empty) == 0.0
    cos, count = masked_cosine_loss(torch.zeros(0, 5), torch.zeros(0, 5), torch.zeros(0, dtype=torch.bool))
    assert count == 0 and float(cos) == 0.0
    cos, count = masked_cosine_loss(torch.ones(3, 5), torch.ones(3, 5), torch.zeros(3, dtype=torch.bool))
    assert count == 0 and float(cos) == 0.0


@pytest.mark.parametrize("weighted", [False, True])
def test_every_row_labelled_skips_the_selection_with_the_same_bits(weighted):
    """With no IGNORE row the logits are used as they are (no selected copy); the value and the rows' gradients
    are bitwise those of the same rows with an ignored row appended (which takes the selecting path)."""
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(50, 6, generator=g, dtype=torch.float64)
    labels = torch.randint(0, 6, (50,), generator=g)
    weights = torch.rand(6, generator=g, dtype=torch.float64) + 0.5 if weighted else None
    every = logits.clone().requires_grad_()
    loss, count = masked_cross_entropy(every, labels, weights)
    loss.backward()
    padded = torch.cat([logits, torch.randn(1, 6, generator=g, dtype=torch.float64)]).requires_grad_()
    loss_padded, count_padded = masked_cross_entropy(padded, torch.cat([labels, torch.tensor([IGNORE_LABEL])]),
                                                     weights)
    loss_padded.backward()
    assert count == count_padded == 50
    assert torch.equal(loss, loss_padded)
    assert torch.equal(every.grad, padded.grad[:50]) and torch.equal(padded.grad[50], torch.zeros(6, dtype=torch.float64))


def test_labels_out_of_range_are_an_error():
    with pytest.raises(ValueError, match="labels must be in 0..2"):
        masked_cross_entropy(torch.zeros(2, 3), torch.tensor([0, 3]))


def test_cosine_loss_hand_computed_and_reference():
    predicted = torch.tensor([[1.0, 0.0], [1.0, 1.0], [0.0, 0.0], [3.0, 4.0]])
    target = torch.tensor([[0.0, 1.0], [2.0, 2.0], [1.0, 0.0], [-3.0, -4.0]])
    valid = torch.tensor([True, True, True, False])
    loss, count = masked_cosine_loss(predicted, target, valid)
    assert count == 3
    assert float(loss) == pytest.approx((1.0 + 0.0 + 1.0) / 3, abs=1e-7)  # a zero vector has cosine 0
    g = torch.Generator().manual_seed(0)
    p, t = torch.randn(30, 6, generator=g, dtype=torch.float64), torch.randn(30, 6, generator=g, dtype=torch.float64)
    v = torch.rand(30, generator=g) < 0.6
    assert float(masked_cosine_loss(p, t, v)[0]) == pytest.approx(reference_cosine_loss(p.tolist(), t.tolist(), v.tolist()),
                                                                  rel=1e-12)


def test_combine_losses_switches():
    t3, t2, cs = (torch.tensor(1.0), 10), (torch.tensor(2.0), 20), (torch.tensor(4.0), 30)
    assert float(combine_losses(t3, t2, cs, no_3dt_align=False, no_vs_align=False).total) == 7.0
    off3 = combine_losses(t3, t2, cs, no_3dt_align=True, no_vs_align=False)
    assert float(off3.total) == 6.0 and off3.count_3d == 0 and float(off3.text_3d) == 0.0
    offv = combine_losses(t3, t2, cs, no_3dt_align=False, no_vs_align=True)
    assert float(offv.total) == 3.0 and offv.count_cosine == 0
    assert float(combine_losses(t3, t2, None, no_3dt_align=False, no_vs_align=False).total) == 3.0
    assert float(combine_losses(t3, t2, cs, no_3dt_align=False, no_vs_align=False, cosine_weight=0.5).total) == 5.0


def test_weighted_cross_entropy_is_the_weighted_sum_over_the_row_count():
    logits = torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.0, -1.0], [5.0, 5.0, 5.0], [0.0, 1.0, 0.0]])
    labels = torch.tensor([2, 0, IGNORE_LABEL, 1])
    weights = torch.tensor([0.5, 2.0, 1.5])
    loss, count = masked_cross_entropy(logits, labels, weights)
    rows = [(logits[0].tolist(), 2), (logits[1].tolist(), 0), (logits[3].tolist(), 1)]
    expected = sum(float(weights[y]) * reference_cross_entropy([row], [y]) for row, y in rows) / 3
    assert count == 3 and float(loss) == pytest.approx(expected, rel=1e-6)
    plain, _ = masked_cross_entropy(logits, labels, torch.ones(3))
    assert float(plain) == pytest.approx(float(masked_cross_entropy(logits, labels)[0]), rel=1e-7)


# --- transductive: partial-label term of the unlabelled rows -----------------------------------------


def test_partial_label_term_hand_computed_and_its_limits():
    logits = torch.tensor([[1.0, 2.0, 3.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    total = math.e + math.e ** 2 + math.e ** 3 + 1.0
    got = partial_label_nll(logits, torch.tensor([2, 3]))
    assert float(got[0]) == pytest.approx(-math.log((math.e ** 3 + 1.0) / total), rel=1e-6)
    assert float(got[1]) == pytest.approx(math.log(2.0), rel=1e-6)
    # every column a candidate: nothing to learn; one candidate: the plain cross-entropy of that column
    assert torch.allclose(partial_label_nll(logits, torch.arange(4)), torch.zeros(2), atol=1e-6)
    plain, _ = masked_cross_entropy(logits[:1], torch.tensor([1]))
    assert float(partial_label_nll(logits[:1], torch.tensor([1]))[0]) == pytest.approx(float(plain), rel=1e-6)
    extreme = partial_label_nll(torch.tensor([[1e4, -1e4, 0.0]]), torch.tensor([1, 2]))
    assert torch.isfinite(extreme).all() and float(extreme[0]) == pytest.approx(1e4, rel=1e-6)


@pytest.mark.parametrize("seed", range(4))
def test_text_cross_entropy_with_unlabelled_rows_matches_reference_forward_and_backward(seed):
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(40, 7, generator=g, dtype=torch.float64) * 5
    labels = torch.randint(0, 5, (40,), generator=g)  # columns 5, 6: the unseen classes, never a label
    labels[torch.rand(40, generator=g) < 0.4] = IGNORE_LABEL
    weights = torch.rand(7, generator=g, dtype=torch.float64) + 0.5
    columns = torch.tensor([5, 6])
    loss, count = text_cross_entropy(logits, labels, weights, columns, 0.7)
    assert count == 40
    assert float(loss) == pytest.approx(reference_text_cross_entropy(
        logits.tolist(), labels.tolist(), weights.tolist(), [5, 6], 0.7), rel=1e-12)
    leaf = logits.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: text_cross_entropy(x, labels, weights, columns, 0.7)[0], (leaf,))


def test_text_cross_entropy_without_unlabelled_columns_is_the_masked_one_bitwise():
    g = torch.Generator().manual_seed(9)
    logits = torch.randn(30, 6, generator=g)
    labels = torch.randint(0, 6, (30,), generator=g)
    labels[::3] = IGNORE_LABEL
    weights = torch.rand(6, generator=g) + 0.5
    a, ca = text_cross_entropy(logits, labels, weights)
    b, cb = masked_cross_entropy(logits, labels, weights)
    assert ca == cb == 20 and torch.equal(a, b)
    # no IGNORE row: the unlabelled term adds nothing
    c, cc = text_cross_entropy(logits[1::3], labels[1::3], weights, torch.tensor([4, 5]))
    d, cd = masked_cross_entropy(logits[1::3], labels[1::3], weights)
    assert cc == cd and torch.equal(c, d)
    # only IGNORE rows: the mean of their partial-label terms, finite
    e, ce = text_cross_entropy(logits[::3], labels[::3], weights, torch.tensor([4, 5]), 2.0)
    assert ce == 10
    assert float(e) == pytest.approx(2.0 * float(partial_label_nll(logits[::3], torch.tensor([4, 5])).mean()), rel=1e-6)


@pytest.mark.parametrize("seed", range(4))
def test_lovasz_softmax_matches_reference_forward_and_backward(seed):
    generator = torch.Generator().manual_seed(seed)
    rows, classes = 23, 5
    logits = (torch.randn(rows, classes, generator=generator, dtype=torch.float64) * 2).requires_grad_(True)
    labels = torch.randint(0, classes - 1, (rows,), generator=generator)  # the last class is never present
    labels[torch.rand(rows, generator=generator) < 0.2] = IGNORE_LABEL
    loss = lovasz_softmax(logits, labels)
    expected = reference_lovasz_softmax(logits.tolist(), labels.tolist())
    assert float(loss) == pytest.approx(expected, rel=1e-12, abs=1e-14)
    (gradient,) = torch.autograd.grad(loss, logits)
    step = 1e-6
    for r in range(rows):
        for c in range(classes):
            plus, minus = logits.detach().clone(), logits.detach().clone()
            plus[r, c] += step
            minus[r, c] -= step
            numeric = (reference_lovasz_softmax(plus.tolist(), labels.tolist())
                       - reference_lovasz_softmax(minus.tolist(), labels.tolist())) / (2 * step)
            assert float(gradient[r, c]) == pytest.approx(numeric, abs=1e-6), (r, c)
    assert bool((gradient[labels == IGNORE_LABEL] == 0).all())


def test_lovasz_softmax_of_one_hot_predictions_is_one_minus_iou():
    predicted = torch.tensor([0, 0, 1, 1, 1, 2, 0, 2])
    labels = torch.tensor([0, 1, 1, 1, 0, 0, IGNORE_LABEL, 1])
    logits = torch.nn.functional.one_hot(predicted, 4).double() * 200.0  # softmax is one-hot to 1e-80
    # present classes 0 and 1: class 0 predicted on rows 0, 1 (row 6 is ignored), true on rows 0, 4, 5 -> IoU 1/4;
    # class 1 predicted on rows 2, 3, 4, true on rows 1, 2, 3, 7 -> IoU 2/5. Class 2 is predicted but not present.
    expected = ((1 - 1 / 4) + (1 - 2 / 5)) / 2
    assert float(lovasz_softmax(logits, labels)) == pytest.approx(expected, abs=1e-12)
    perfect = torch.nn.functional.one_hot(torch.where(labels == IGNORE_LABEL, 3, labels), 4).double() * 200.0
    assert float(lovasz_softmax(perfect, labels)) == pytest.approx(0.0, abs=1e-12)


def test_lovasz_softmax_empty_extreme_and_bad_labels():
    logits = torch.randn(4, 3, requires_grad=True)
    empty = lovasz_softmax(logits, torch.full((4,), IGNORE_LABEL))
    assert float(empty) == 0.0
    (gradient,) = torch.autograd.grad(empty, logits)
    assert bool((gradient == 0).all())
    extreme = torch.tensor([[1e4, -1e4, 0.0], [-3e38, 3e38, 0.0]], requires_grad=True)
    loss = lovasz_softmax(extreme, torch.tensor([1, 1]))
    loss.backward()
    assert math.isfinite(float(loss)) and bool(torch.isfinite(extreme.grad).all())
    with pytest.raises(ValueError, match="labels must be in"):
        lovasz_softmax(torch.zeros(2, 3), torch.tensor([0, 3]))
