"""Bootstrap intervals over scenes: the vectorized draws against the slow loop, and their protocol."""

import numpy as np
import pytest

from types import SimpleNamespace

from ovgaussian.bench import baselines as baseline
from ovgaussian.bench.evaluate import evaluate, metric_interval, result_to_dict
from ovgaussian.bench.bootstrap import (
    bootstrap_miou, bootstrap_miou_reference, bootstrap_ratio, bootstrap_ratio_reference, draw_scene_counts,
    miou_of_stack, overlaps,
)
from ovgaussian.metrics import scores_from_confusion
from ovgaussian.text.vocabulary import make_vocabulary
from seggaussian.core.constants import read_class_names
from seggaussian.core.gaussians import Gaussians

NAMES = read_class_names()
ID = {n: NAMES.index(n) for n in NAMES}
VOCAB = make_vocabulary([ID["wall"], ID["floor"], ID["chair"], ID["curtain"], ID["bookshelf"], ID["sofa"], ID["bed"]])


def random_scenes(rng, scenes, k, empty_classes=()):
    """``[S, K, K+1]`` counts: mostly diagonal, some confusions and misses, some classes absent."""
    mats = rng.integers(0, 4, size=(scenes, k, k + 1))
    mats[:, np.arange(k), np.arange(k)] += rng.integers(0, 40, size=(scenes, k))
    for c in empty_classes:
        mats[:, c, :] = 0
        mats[:, :, c] = 0
    return mats.astype(np.int64)


@pytest.mark.parametrize("seed", range(5))
def test_vectorized_bootstrap_equals_the_loop(seed):
    rng = np.random.default_rng(seed)
    per_scene = random_scenes(rng, scenes=int(rng.integers(2, 9)), k=6, empty_classes=(4,))
    classes = [0, 2, 3, 4] if seed % 2 else None
    fast = bootstrap_miou(per_scene, classes, draws=300, seed=seed)
    slow = bootstrap_miou_reference(per_scene, classes, draws=300, seed=seed)
    assert fast.draws == slow.draws == 300 and fast.scenes == slow.scenes
    assert fast.value == pytest.approx(slow.value, abs=1e-12)
    assert fast.low == pytest.approx(slow.low, abs=1e-12) and fast.high == pytest.approx(slow.high, abs=1e-12)
    assert fast.low <= fast.value <= fast.high


def test_stack_miou_follows_scores_from_confusion_with_absent_and_predicted_only_classes():
    rng = np.random.default_rng(1)
    mats = random_scenes(rng, scenes=12, k=5, empty_classes=(1, 3))
    mats[2, 0, 3] = 7  # class 3 predicted but never present: IoU 0, counts in the mean
    classes = np.array([0, 1, 3, 4])
    fast = miou_of_stack(mats, classes)
    for b in range(12):
        assert fast[b] == pytest.approx(scores_from_confusion(mats[b], classes).miou, abs=1e-12)
    empty = np.zeros((1, 5, 6), np.int64)
    assert np.isnan(miou_of_stack(empty, classes)[0]) and scores_from_confusion(empty[0], classes).miou is None


def test_draws_are_resamples_of_all_scenes():
    counts = draw_scene_counts(7, 500, seed=3)
    assert counts.shape == (500, 7) and (counts.sum(axis=1) == 7).all() and counts.min() >= 0
    assert (draw_scene_counts(7, 500, seed=3) == counts).all()  # seeded
    assert counts.mean(axis=0) == pytest.approx(np.ones(7), abs=0.15)  # each scene picked once on average


def test_identical_scenes_give_a_point_interval_and_one_scene_none():
    one = random_scenes(np.random.default_rng(2), scenes=1, k=4)
    same = np.repeat(one, 6, axis=0)
    interval = bootstrap_miou(same, draws=200)
    assert interval.low == pytest.approx(interval.value) and interval.high == pytest.approx(interval.value)
    single = bootstrap_miou(one, draws=200)
    assert single.value is not None and single.low is None and single.high is None


def test_interval_narrows_with_more_scenes_and_covers_the_truth():
    # scenes whose accuracy varies around a known mean: more scenes, a tighter interval around it
    rng = np.random.default_rng(4)

    def scenes(n):
        mats = np.zeros((n, 2, 3), np.int64)
        right = rng.integers(60, 100, size=n)
        mats[:, 0, 0], mats[:, 0, 1] = right, 100 - right
        mats[:, 1, 1] = 100
        return mats

    small, large = bootstrap_miou(scenes(5), draws=1000), bootstrap_miou(scenes(80), draws=1000)
    assert (large.high - large.low) < (small.high - small.low)
    assert large.low < large.value < large.high


@pytest.mark.parametrize("seed", [0, 3])
def test_paired_ratio_equals_the_loop(seed):
    rng = np.random.default_rng(seed)
    top, bottom = random_scenes(rng, 9, 6, empty_classes=(4,)), random_scenes(rng, 9, 6, empty_classes=(4,))
    fast = bootstrap_ratio(top, bottom, draws=300, seed=seed)
    slow = bootstrap_ratio_reference(top, bottom, draws=300, seed=seed)
    assert fast.value == pytest.approx(slow.value, abs=1e-12)
    assert (fast.low, fast.high, fast.draws) == pytest.approx((slow.low, slow.high, slow.draws), abs=1e-12)
    assert fast.value == pytest.approx(scores_from_confusion(top.sum(0)).miou / scores_from_confusion(bottom.sum(0)).miou)
    assert fast.low <= fast.value <= fast.high


def test_paired_ratio_is_tighter_than_unpaired_when_the_rooms_carry_the_spread():
    # Both sides score the same rooms; a room hard for one is hard for the other (the numerator is the
    # denominator with a tenth of every diagonal moved to a miss). The paired ratio stays near its value; the
    # two mIoUs' own intervals are wide.
    rng = np.random.default_rng(1)
    bottom = random_scenes(rng, 12, 5)
    bottom[1::2, np.arange(5), np.arange(5)] //= 6  # every other room hard
    top = bottom.copy()
    moved = top[:, np.arange(5), np.arange(5)] // 10
    top[:, np.arange(5), np.arange(5)] -= moved
    top[:, np.arange(5), 5] += moved
    paired = bootstrap_ratio(top, bottom, draws=500)
    alone = bootstrap_miou(bottom, draws=500)
    assert paired.high - paired.low < 0.5 * (alone.high - alone.low) / alone.value


def test_paired_ratio_refuses_unpaired_sets_and_has_no_interval_for_one_room():
    rng = np.random.default_rng(2)
    with pytest.raises(ValueError, match="same scenes"):
        bootstrap_ratio(random_scenes(rng, 4, 3), random_scenes(rng, 5, 3))
    one = bootstrap_ratio(random_scenes(rng, 1, 3), random_scenes(rng, 1, 3))
    assert one.value is not None and one.low is None and one.high is None
    empty = np.zeros((3, 3, 4), np.int64)
    assert bootstrap_ratio(random_scenes(rng, 3, 3), empty).value is None


def test_overlap():
    from ovgaussian.bench.bootstrap import Interval

    a, b, c = Interval(0.5, 0.4, 0.6, 10, 5), Interval(0.7, 0.61, 0.8, 10, 5), Interval(0.55, 0.5, 0.65, 10, 5)
    assert overlaps(a, b) is False and overlaps(a, c) is True and overlaps(a, Interval(0.1, None, None, 0, 1)) is None


class Truth(baseline.GroundTruthPredictor):
    """Per-Gaussian one-hot of the label, with chairs of the scene ids listed in ``as_wall`` called wall."""

    name = "truth"

    def __init__(self, as_wall=()):
        self.as_wall = set(as_wall)

    def encode(self, scene):
        out = super().encode(scene)
        if scene.scene_id in self.as_wall:
            out[:, ID["wall"]] += out[:, ID["chair"]]
            out[:, ID["chair"]] = 0.0
        return out


def scene(scene_id, labels):
    n = len(labels)
    g = Gaussians.from_arrays(np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), -3.0), np.zeros(n),
                              np.zeros((n, 1, 3), np.float32), extras={"semantic": np.asarray(labels, np.int32)})
    return SimpleNamespace(scene_id=scene_id, source="synthetic", gaussians=g, views=[])


def test_bench_keeps_one_matrix_per_scene_and_reports_the_interval():
    w, f, c = ID["wall"], ID["floor"], ID["chair"]
    data = {"val": [scene(f"v{i}", [w, w, f, c, c]) for i in range(6)], "train": [scene("t0", [w, c])],
            "xval": [scene("x0", [w, f])]}
    result = evaluate(Truth(as_wall={"v0", "v1", "v2"}), data, VOCAB, dims=("3d",), metrics=("CSA", "CDA"))
    for key, total in result.confusion.items():
        assert (result.scene_confusion[key].sum(axis=0) == total).all()
    assert result.scene_confusion[("val", "3d")].shape == (6, 7, 8)
    interval = metric_interval(result, "3d", "CSA")
    assert interval.value == pytest.approx(result.results[("3d", "CSA")].scores.miou)
    assert interval.low < interval.value < interval.high  # half the scenes are wrong on chairs
    same = bootstrap_miou_reference(result.scene_confusion[("val", "3d")], result.results[("3d", "CSA")].classes)
    assert (same.low, same.high) == pytest.approx((interval.low, interval.high))
    payload = result_to_dict(evaluate(Truth(), data, VOCAB, dims=("3d",), metrics=("CSA", "CDA")))
    assert payload["metrics"]["3d"]["CSA"]["ci95"] == [1.0, 1.0]
    assert payload["metrics"]["3d"]["CDA"]["ci95"] is None  # one xval scene: no interval
    assert len(payload["scene_confusion"]["val_3d"]) == 6
